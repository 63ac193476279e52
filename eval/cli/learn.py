"""`cosim` commands that train and evaluate: train (and PBT), test, benchmark, replay
(the parser is in eval/cli/__init__.py)."""

from __future__ import annotations

import contextlib
import os
import re
import sys
from pathlib import Path

from eval.training.runfolder import output_folder

OWNER_ENV = "COSIM_OWNER_PID"
"""Set by ``cosim train --algo all`` for its per-algorithm commands: the pid they die with."""


@contextlib.contextmanager
def _terminate_as_interrupt():
    """SIGTERM handled as Ctrl-C while a command runs: KeyboardInterrupt, so its cleanup runs
    (simulators and workers closed, the run folder left resumable) and `cosim` says
    "cosim: interrupted" (exit 130). The previous handler comes back after."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _die_with_parent() -> None:
    """A per-algorithm command of ``--algo all`` (:data:`OWNER_ENV` set): SIGTERM (stop
    resumably) when that parent dies, even by kill -9."""
    owner = os.environ.pop(OWNER_ENV, "")
    if owner.isdigit():
        import signal

        from agents.workers import die_with_owner

        die_with_owner(int(owner), sig=signal.SIGTERM)


def cmd_train(args) -> int:
    _die_with_parent()
    with _terminate_as_interrupt():
        return _cmd_train(args)


def _cmd_train(args) -> int:
    from eval.training.train import TrainError, resolve, train

    if args.pbt is not None or (args.resume is not None and (args.resume / "pbt.json").exists()):
        return _train_pbt(args)
    try:
        if args.resume is not None:
            run = train(None, resume=args.resume, quiet=args.quiet, keep=args.keep, steps=args.steps)
            print(f"run folder: {run}")
            return 0
        options = _run_options(args)
        if options.init_from is not None and options.algo == "all":
            raise TrainError("--init-from warm-starts one algorithm from its own run; choose it with --algo")
        if (options.demo_steps or options.demo_updates) and options.algo == "all":
            raise TrainError("--demo-steps fills one replay learner's buffer; choose it with --algo dqn, ddpg or td3")
        runs = [options.for_algo(a) for a in options.algos] if options.algo == "all" else [options]
        configs = [resolve(o) for o in runs]  # every refusal before the first run starts
    except TrainError as exc:
        print(f"cosim train: error: {exc}", file=sys.stderr)
        return 2
    if len(configs) == 1:
        try:
            run = train(configs[0], args.out, quiet=args.quiet, keep=args.keep)
        except TrainError as exc:
            print(f"cosim train: error: {exc}", file=sys.stderr)
            return 2
        print(f"run folder: {run}")
        return 0
    return _train_all(args, runs, configs)


def _run_options(args):
    """The run options of a `cosim train` command line (eval/training/options.py), or those an
    ``--algo all`` parent handed this run (``--options JSON``, then no run-option flag may be given).

    Raises:
        TrainError: a refused option, or ``--options`` beside run-option flags.
    """
    from eval.training.options import RunOptions, TrainError, declared

    flags = RunOptions.from_args(args)
    if args.options is None:
        return flags
    if flags != RunOptions():
        given = " ".join(spec.flag for name, spec in declared() if name in flags.changed())
        raise TrainError(f"--options holds the run's options: give {given} there, not as flags beside it")
    return RunOptions.from_json(args.options)


LINE = re.compile(r"^\[(?P<algo>\w+) \S+\] step (?P<step>\d+)/(?P<steps>\d+)")
"""A --quiet training run's progress line (eval/training/trainer.py, _report)."""


def _train_all(args, runs, configs) -> int:
    """``cosim train --algo all``: one `cosim train --quiet` process per algorithm, started with
    its run options (``runs``, RunOptions.for_algo; ``configs``, what they resolve to), as many
    at once as there are CPUs, under one progress bar over all their steps (their log lines,
    every few seconds, move it; other lines are printed above it; ``--quiet``: the lines only)."""
    import queue
    import subprocess
    import threading

    from tqdm import tqdm

    parallel = max(1, os.cpu_count() or 1)
    print(f"training {len(configs)} algorithms, {parallel} at a time", flush=True)
    steps = {c.algo: c.steps for c in configs}
    pending = [c.algo for c in configs]
    options = {o.algo: o for o in runs}
    running: dict[str, subprocess.Popen] = {}
    done_steps = dict.fromkeys(steps, 0)
    failed, lines = [], queue.Queue()
    bar = tqdm(total=sum(steps.values()), unit="step", desc="train all", dynamic_ncols=True,
               disable=args.quiet, smoothing=0.05)
    say = print if args.quiet else bar.write
    env = {**os.environ, "PYTHONUNBUFFERED": "1", OWNER_ENV: str(os.getpid())}  # they die with this process
    if not args.quiet:  # their lines move the bar: a line every few seconds
        env["COSIM_LOG_EVERY_S"] = os.environ.get("COSIM_LOG_EVERY_S", "5")

    def pump(algo: str, stream) -> None:
        for text in stream:
            lines.put((algo, text.rstrip("\n")))

    def advance(algo: str, step: int) -> None:
        step = min(step, steps[algo])
        bar.update(step - done_steps[algo])
        done_steps[algo] = step
        bar.set_postfix_str(" ".join(f"{a} {done_steps[a] * 100 // steps[a]}%" for a in running), refresh=False)

    def handle(algo: str, text: str) -> None:
        hit = LINE.match(text)
        if text.startswith("run folder: "):
            folders[algo] = text.removeprefix("run folder: ")
        elif hit and not args.quiet:
            advance(algo, int(hit["step"]))
        else:
            say(text if hit else f"[{algo}] {text}")

    def drain(timeout: float = 0.0) -> None:
        try:
            while True:
                handle(*lines.get(timeout=timeout))
                timeout = 0.0
        except queue.Empty:
            pass

    folders: dict[str, str] = {}
    pumps: dict[str, threading.Thread] = {}
    try:
        while pending or running:
            while pending and len(running) < parallel:
                algo = pending.pop(0)
                running[algo] = subprocess.Popen(_child_command(args, options[algo]), stdout=subprocess.PIPE,
                                                 text=True, env=env)
                pumps[algo] = threading.Thread(target=pump, args=(algo, running[algo].stdout), daemon=True)
                pumps[algo].start()
            drain(timeout=0.5)
            for algo, proc in list(running.items()):
                if proc.poll() is None:
                    continue
                pumps[algo].join(timeout=10)  # its last lines (the run folder) are read
                drain()
                del running[algo]
                if proc.returncode == 0:
                    advance(algo, steps[algo])
                    say(f"{algo}: done, run folder {folders.get(algo, '?')}")
                else:
                    say(f"{algo}: FAILED (exit {proc.returncode})")
                    failed.append(algo)
    except BaseException:  # Ctrl-C, SIGTERM: the runs still training stop resumably
        bar.close()
        _say_stopping(list(running), args.out)
        raise
    finally:
        _stop_children(list(running.values()))
        bar.close()
    return 1 if failed else 0


def _say_stopping(algos: list[str], out) -> None:
    """What an interrupted ``--algo all`` says of the runs it stops (nothing when none runs)."""
    if algos:
        print(f"cosim train: stopping {', '.join(algos)}; their runs resume with "
              f"`cosim train --resume RUN` (run folders under {out})", file=sys.stderr, flush=True)


def _child_command(args, options) -> list[str]:
    """The `cosim train` process of one algorithm of ``--algo all``: its run options as one JSON
    object (RunOptions.to_json), where its run folder goes and what it keeps."""
    return [sys.executable, "-m", "eval.cli", "train", "--options", options.to_json(), "--out", str(args.out),
            "--keep", args.keep, "--quiet"]


def _stop_children(procs, grace_s: float = 30.0) -> None:
    """SIGTERM each child (a `cosim train` stops as on Ctrl-C), wait up to ``grace_s`` for them
    all, then SIGKILL the rest and reap them: none outlives this process."""
    import subprocess
    import time

    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    deadline = time.monotonic() + grace_s
    for proc in procs:
        try:
            proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _train_pbt(args) -> int:
    from eval.scale.pbt import run_pbt
    from eval.scale.raysession import ray_available
    from eval.training.train import TrainError, resolve

    if not ray_available():
        print("cosim train: error: --pbt needs Ray Tune, which is not installed; install it with: "
              "pip install -e '.[tune]'", file=sys.stderr)
        return 2
    try:
        cfg = None
        if args.resume is None:
            options = _run_options(args)
            if options.algo == "all":
                raise TrainError("--pbt trains one algorithm; choose it with --algo")
            # the trials share the CPUs: at least one torch thread each
            cfg = resolve(options.replace(torch_threads=options.torch_threads or 1))
        folder = run_pbt(cfg, args.pbt or 0, args.pbt_interval, args.out, resume=args.resume,
                         address=args.ray_address)
    except TrainError as exc:
        print(f"cosim train: error: {exc}", file=sys.stderr)
        return 2
    print(f"lineage: {folder / 'lineage.csv'}  {folder / 'lineage.png'}")
    print(f"run folder (best trial): {folder}")
    return 0


def cmd_test(args) -> int:
    with _terminate_as_interrupt():
        return _cmd_test(args)


def _cmd_test(args) -> int:
    import datetime as dt

    from eval.testing.protocol import ALGO_ORDER, ProtocolError, ProtocolPlan
    from eval.testing.validity import POLICIES

    if args.algos:  # paper order, one AC each
        args.agents = len(set(args.algos))
    if not 1 <= args.agents <= 6:
        print("cosim test: error: --agents must be 1..6 (one AC per algorithm)", file=sys.stderr)
        return 2
    refs_wanted = (list(POLICIES) if args.references == "all" else []
                   if args.references == "none" else args.references.split(","))
    unknown = sorted(set(refs_wanted) - set(POLICIES))
    if unknown:
        print(f"cosim test: error: --references {','.join(unknown)}: unknown; valid: all, none, "
              f"or a comma list of {', '.join(POLICIES)}", file=sys.stderr)
        return 2
    scenarios = (1, 2) if args.scenario == "both" else (int(args.scenario),)
    plan = ProtocolPlan(envs=tuple(args.envs), scenarios=scenarios, episodes=args.episodes, steps=args.steps,
                        seed=args.seed, agents=args.agents, rotate=not args.fixed_slots, greedy=args.greedy)
    algos = [a for a in ALGO_ORDER if a in args.algos] if args.algos else list(ALGO_ORDER[: args.agents])
    from cosim.scenario import load_scenario

    for env_name in plan.envs:  # a bad name fails now, not after the first environments ran
        load_scenario(env_name)
    try:
        request = _test_request(args, plan, algos, refs_wanted)
        _ = request.policies  # each checkpoint loads now: a bad file fails before the folder is made
    except ProtocolError as exc:
        print(f"cosim test: error: {exc}", file=sys.stderr)
        return 2
    return _write_test(args, request, _test_folder(args, dt.datetime.now().strftime("%Y%m%d-%H%M%S")))


def _test_request(args, plan, algos: list[str], references: list[str]):
    """The test session `cosim test`'s options ask for (eval.testing.session.TestRequest).

    Raises:
        ProtocolError: a bad --sweep or --checkpoint, no checkpoint, or a cross-environment test
            without --allow-cross-env.
    """
    from eval.reporting.report import slot_label
    from eval.testing.protocol import ProtocolError
    from eval.testing.robustness import parse_sweeps
    from eval.testing.session import TestRequest

    sweeps = parse_sweeps(args.sweep)
    given = _checkpoint_slots(args.checkpoint, algos)
    if given and args.policy != "trained":
        raise ProtocolError(f"--checkpoint is for --policy trained, not --policy {args.policy}")
    return TestRequest(plan, tuple(algos), checkpoints=_test_checkpoints(args, plan, algos, given),
                       policy=args.policy, fixed=tuple(given), references=tuple(references),
                       replays=not args.no_replays, labels={a: slot_label(args.policy, a) for a in algos},
                       cross_play=args.cross_play_group if args.cross_play else 0, sweeps=sweeps,
                       workers=args.workers, encoder=None if args.encoder is None else str(args.encoder))


def _write_test(args, request, out: Path) -> int:
    """Run `cosim test`'s session into ``out`` (eval.testing.session.run_test), then its report."""
    from eval.reporting.report import provenance, write_paper_report
    from eval.testing import selection
    from eval.testing.protocol import ProtocolError
    from eval.testing.session import run_test
    from eval.testing.slots import slot_summary, slots_markdown

    plan, algos, given = request.plan, list(request.algos), request.fixed
    slots = request.slots
    if slots is not None:  # which checkpoint drives which slot where: console and report
        print(f"checkpoints per environment and slot (slots.csv):\n{slot_summary(slots)}")
        slots.to_csv(out / "slots.csv", index=False)
    # provenance first: the code, checkpoints and hashes as they are when the test starts
    ckpts = request.checkpoints[plan.envs[0]] if request.checkpoints else None
    picked = {a: selection.describe(p) if a in given else
              (selection.choose(p.parent.parent.parent) or selection.describe(p))
              for a, p in (ckpts or {}).items()}
    prov = provenance(policy=request.policy, plan=plan, algos=algos, checkpoints=ckpts,
                      selections=picked, command=_test_command(args))
    if slots is not None:
        prov["slots"] = slots.to_dict("records")
    phases = _Phases(args.quiet)
    try:  # each run's episodes kept as it ends: an interrupted test goes on from them
        result = run_test(request, out, phases.bar)
    except KeyboardInterrupt:
        phases.close()
        kept = len(list((out / "episodes").glob("job-*.parquet")))
        print(f"cosim test: stopped; {out} is incomplete ({INCOMPLETE}), the episodes of {kept} finished "
              f"run(s) kept in {out / 'episodes'}: the same command with --out {out} runs the rest",
              file=sys.stderr, flush=True)
        raise
    extra_md = slots_markdown(slots) if slots is not None else ""
    if result.cross_play is not None or result.sweeps:
        from eval.reporting import robustness as robustness_report

        extra_md += robustness_report.write(out, dict(request.labels), result.cross_play, result.sweeps)[1]
    phases.say("writing the report (tables, figures) ...")
    try:
        written = write_paper_report(result.records, out, prov=prov, references=result.references,
                                     replays=result.replays, extra_md=extra_md)
    except OSError as exc:  # a full disk: the episodes stay in episodes/, the folder incomplete
        phases.close()
        raise ProtocolError(f"cannot write the report in {out} ({exc.strerror or exc}: {exc.filename or out}); "
                            f"free space (or fix the folder), then the same command with --out {out} "
                            "writes it from the episodes kept") from exc
    import shutil

    shutil.rmtree(out / "episodes", ignore_errors=True)  # in records.parquet now
    (out / INCOMPLETE).unlink(missing_ok=True)
    phases.close()
    print((out / "rq1.md").read_text())
    print(f"index: {out / 'index.html'}")
    print("wrote:\n" + "\n".join(f"  {p}" for p in [*written, *([out / "slots.csv"] if slots is not None else [])]))
    return 0


INCOMPLETE = "incomplete.json"
"""In a `cosim test` report folder until its report is written: the folder is not a report yet
(interrupted, or running), its finished runs' episodes in episodes/ (eval.testing.jobs
run_protocol's ``save``); `cosim test` with the same options and ``--out`` that folder goes on."""


def _test_folder(args, stamp: str) -> Path:
    """The report folder of a `cosim test`: ``--out`` itself where it is an incomplete report
    folder of the same test (:data:`INCOMPLETE`: go on from its episodes), else a new
    ``--out/<stamp>`` marked incomplete until its report is written.

    Raises:
        ProtocolError: ``--out`` is an incomplete folder of a test with other options.
    """
    import json

    from eval.testing.protocol import ProtocolError
    from eval.training.runfolder import atomic_write

    command = _test_command(args)
    at = command.index("--out")
    del command[at: at + 2]  # without --out: the folder it names differs on a resume
    marker = args.out / INCOMPLETE
    if marker.is_file():
        try:
            started = json.loads(marker.read_text())["command"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ProtocolError(f"{marker} is unreadable ({type(exc).__name__}); delete {args.out} "
                                "and run the test again") from None
        if started != command:
            raise ProtocolError(f"{args.out} holds an incomplete test run as `cosim {' '.join(started)}`; "
                                "give those options to finish it, or another --out")
        print(f"cosim test: going on with the incomplete test in {args.out}", file=sys.stderr)
        return args.out
    out = output_folder(args.out / stamp, "--out")
    atomic_write(out / INCOMPLETE, json.dumps({"command": command, "note": (
        "this test has not finished writing its report; the episodes of its finished runs are in "
        f"episodes/; `cosim test` with the same options and --out {out} runs the rest")}, indent=1))
    return out


def _test_checkpoints(args, plan, algos: list[str], given: dict[str, Path]) -> dict | None:
    """The checkpoints each environment is tested with (environment -> algorithm -> path; None
    for a reference policy). Each environment takes the newest run of each algorithm trained
    in it; a checkpoint trained in another environment (none of its own under --runs, or a
    --checkpoint from another) is refused without --allow-cross-env, and named on stderr with it.

    Raises:
        ProtocolError: no checkpoint, or a cross-environment test without --allow-cross-env.
    """
    from eval.testing.checkpoints import cross_env, find_checkpoints
    from eval.testing.protocol import ProtocolError

    if args.policy != "trained":
        return None
    per_env = {}
    for env in plan.envs:
        found = find_checkpoints(args.runs, [a for a in algos if a not in given], env=env)
        per_env[env] = {a: (given.get(a) or found[a]) for a in algos}
    crossed = cross_env(per_env)
    by_ckpt: dict[tuple, list[str]] = {}
    for algo, path, trained, env in crossed:
        by_ckpt.setdefault((algo, path, trained), []).append(env)
    if by_ckpt and not args.allow_cross_env:
        (algo, path, trained), envs = next(iter(by_ckpt.items()))
        more = f" ({len(by_ckpt) - 1} more checkpoint(s) likewise)" if len(by_ckpt) > 1 else ""
        raise ProtocolError(
            f"the {algo} checkpoint {path} was trained in {trained}, not in {' '.join(envs)}{more}; "
            f"train {algo} there (`cosim train --algo {algo} --env {envs[0]}`), test the environment "
            f"it was trained in (--envs {trained}), or pass --allow-cross-env to test it in "
            f"{' '.join(envs)} anyway")
    for (algo, path, trained), envs in by_ckpt.items():
        print(f"cosim test: warning: the {algo} checkpoint {path} was trained in {trained} and drives "
              f"{' '.join(envs)} (--allow-cross-env)", file=sys.stderr)
    return per_env


class _Phases:
    """Progress of `cosim test`'s phases (test, references, replays, cross-play, sweeps): a
    tqdm bar each, as the training bar (eval/training/trainer.py); a line per phase that
    starts without one (the report)."""

    def __init__(self, quiet: bool):
        self.quiet, self._bar = quiet, None

    def bar(self, desc: str, total: int | None, unit: str):
        from tqdm import tqdm

        self.close()
        self._bar = tqdm(total=total, disable=self.quiet, unit=unit, desc=desc, dynamic_ncols=True)
        return lambda name: (self._bar.set_postfix_str(name, refresh=False), self._bar.update(1))

    def say(self, text: str) -> None:
        self.close()
        if not self.quiet:
            print(text, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def cmd_benchmark(args) -> int:
    import time

    from eval.scale.benchmark import (
        BenchmarkError,
        BenchmarkPlan,
        finished_cells,
        finished_runs,
        report_steps,
        run_ray,
        run_sequential,
        write_report,
    )
    from eval.scale.raysession import INSTALL_HINT, ray_available
    from eval.training.options import TrainError

    if args.status:
        from eval.scale.benchmark import load_plan
        from eval.scale.gridstatus import grid_status, status_text

        print(status_text(grid_status(args.out), plan=load_plan(args.out)))
        return 0
    if not args.no_ray and not ray_available():
        print(f"cosim benchmark: error: {INSTALL_HINT}", file=sys.stderr)
        return 2
    from eval.training.options import RunOptions

    try:
        options = RunOptions.from_args(args, "benchmark")
    except TrainError as exc:  # as the plan's own refusals: one line, exit 2
        raise BenchmarkError(str(exc)) from None
    plan = BenchmarkPlan(envs=tuple(args.envs), algos=tuple(args.algos), seeds=args.seeds,
                         first_seed=args.first_seed, options=options)
    cells = plan.cells()  # a bad environment or algorithm fails here, before Ray starts
    output_folder(args.out, "--out")
    say = (lambda text: None) if args.quiet else (lambda text: print(text, flush=True))
    # finished earlier: in runs/, or (Tune moves runs there only when the whole grid ends) a
    # trial at its budget; --no-ray finishes and counts such a trial itself
    kept = len((finished_runs if args.no_ray else finished_cells)(plan, args.out))
    start = time.monotonic()
    say(f"benchmark {args.preset}: {len(cells)} trials ({kept} finished earlier, kept) -> {args.out}")
    if args.no_ray:
        runs = run_sequential(plan, args.out, resume=args.resume, keep=args.keep,
                              progress=_counted(say, len(cells), kept, prefix="trained "))
    else:
        concurrent = args.concurrent or (0 if args.ray_address else (os.cpu_count() or 1))
        runs = run_ray(plan, args.out, resume=args.resume, address=args.ray_address,
                       concurrent=concurrent, gpus_per_trial=args.gpus_per_trial, keep=args.keep,
                       progress=say)
    say(f"trained {len(runs) - kept} trials in {time.monotonic() - start:.0f} s: {args.out / 'runs'}")
    if args.train_only:
        return 0
    written = write_report(plan, args.out, command=["benchmark", *sys.argv[2:]],
                           progress=_counted(say, report_steps(plan)))
    say(f"report: {args.out / 'report' / 'index.html'} ({len(written)} files, "
        f"{time.monotonic() - start:.0f} s in all)")
    return 0


def _counted(say, total: int, done: int = 0, prefix: str = ""):
    """A progress callback saying ``[k/total] <prefix><what> (<seconds> s)`` per call: the
    seconds since the previous call (what just ended); none for a phase that starts ("... ")."""
    import time

    state = {"count": done, "last": time.monotonic()}

    def report(what: str) -> None:
        now = time.monotonic()
        state["count"] += 1
        took = "" if what.endswith("...") else f" ({now - state['last']:.0f} s)"
        say(f"[{state['count']}/{total}] {prefix}{what}{took}")
        state["last"] = now

    return report


def cmd_replay(args) -> int:
    from eval.testing import replay

    path = args.state
    if not path.exists() or not path.with_suffix(".json").exists():
        print(f"cosim replay: error: {path}: not a failure replay (give the state.json of a "
              "report's replays/ folder)", file=sys.stderr)
        return 2
    problem = _replay_problem(path.with_suffix(".json"))
    if problem:
        print(f"cosim replay: error: {path.with_suffix('.json')}: {problem}; give the state.json of a "
              "report's replays/ folder as `cosim test` wrote it (or write the report again)", file=sys.stderr)
        return 2
    result = replay.reload(path)
    meta = result["meta"]
    print(f"{meta['title']} ({meta['env']}), scenario {meta['scenario']}, {meta['label']} "
          f"({meta['agent']}), episode {meta['episode']} seed {meta['seed']}, step {meta['step']} "
          f"(t = {meta['ttfc']:.1f} s), first collision with a {meta['kind']} {meta['hit']}")
    pos = result["positions"]
    print(f"SUMO time {pos['time']:.1f} s: {len(pos['vehicles'])} vehicles, {len(pos['persons'])} persons")
    for vid, (x, y, angle) in sorted(pos["vehicles"].items()):
        mark = "  <- collided" if vid == meta["agent"] else ""
        print(f"  {vid:24s} x={x:9.2f} y={y:9.2f} angle={angle:6.1f}{mark}")
    for pid, (x, y, _) in sorted(pos["persons"].items()):
        print(f"  {pid:24s} x={x:9.2f} y={y:9.2f} (person)")
    print(f"largest distance from the saved positions: {result['max_deviation_m']:.3f} m")
    if args.plot:
        print(f"wrote {replay.plot(result, args.plot)}")
    return 0


REPLAY_KEYS = ("title", "env", "scenario", "label", "agent", "episode", "seed", "step", "ttfc", "kind",
               "hit", "background", "pedestrians", "state", "positions")
"""What `cosim replay` reads of a failure replay's record (eval/testing/replay.py)."""


def _replay_problem(meta: Path) -> str | None:
    """Why a failure replay's record is not one (unreadable, not JSON, keys missing); None if it is."""
    import json

    try:
        data = json.loads(meta.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        return f"unreadable ({type(exc).__name__})"
    except ValueError as exc:
        return f"not valid JSON ({exc})"
    if not isinstance(data, dict):
        return f"expected a JSON object, got {type(data).__name__}"
    missing = [k for k in REPLAY_KEYS if k not in data]
    if missing:
        return f"not a failure replay's record (no {', '.join(missing)})"
    positions = data["positions"]
    if not (isinstance(positions, dict) and all(isinstance(positions.get(k), dict) for k in ("vehicles", "persons"))):
        return "its 'positions' are not {'vehicles': {...}, 'persons': {...}}"
    return None


def _test_command(args) -> list[str]:
    """The `cosim test` command line the parsed options stand for (for the report)."""
    who = ["--algos", *args.algos] if args.algos else ["--agents", str(args.agents)]
    cmd = ["test", *who, "--envs", *args.envs, "--scenario", args.scenario,
           "--episodes", str(args.episodes), *(["--steps", str(args.steps)] if args.steps is not None else []),
           "--seed", str(args.seed), "--policy", args.policy]
    cmd += ["--runs", str(args.runs)] if args.policy == "trained" else []
    for item in args.checkpoint:
        cmd += ["--checkpoint", item]
    cmd += ["--encoder", str(args.encoder)] if getattr(args, "encoder", None) is not None else []
    cmd += ["--no-replays"] * args.no_replays + ["--greedy"] * args.greedy + ["--fixed-slots"] * args.fixed_slots
    if args.cross_play:
        cmd += ["--cross-play", "--cross-play-group", str(args.cross_play_group)]
    for item in args.sweep:
        cmd += ["--sweep", item]
    return cmd + ["--references", args.references, "--out", str(args.out)]


def _checkpoint_slots(items: list[str], algos: list[str]) -> dict[str, Path]:
    """``["ppo=path.pt", ...]`` (``--checkpoint``) -> ``{"ppo": Path("path.pt")}``."""
    from eval.testing.protocol import ProtocolError

    out = {}
    for item in items:
        algo, sep, path = item.partition("=")
        if not sep or not path:
            raise ProtocolError(f"--checkpoint {item!r}: write ALGO=PATH, e.g. ppo=runs/x/best.pt")
        if algo not in algos:
            raise ProtocolError(f"--checkpoint {item!r}: {algo!r} is not one of the ACs tested "
                                f"({', '.join(algos)}; --agents sets how many)")
        out[algo] = Path(path)
    return out
