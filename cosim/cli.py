"""The `cosim` command line: the only place that wires environments, agents and evaluation.

    cosim scenarios                         list the driving environments
    cosim drive env_3 --agents 6            run the scripted drivers, print events (no cameras)
    cosim view env_3 --out view/            camera mosaic PNG + GIFs of what the ACs see
    cosim nets build | check                rebuild / check the SUMO networks
    cosim train --algo ppo --env env_1      train N ACs of one algorithm together
    cosim test --agents 6                   the test protocol (Scenario 1 and 2) and its report
    cosim benchmark --preset smoke          train the grid on Ray Tune, test it, write the report
    cosim replay REPORT/replays/X/state.json  reopen a failure replay's SUMO state
    cosim check-scenarios env_4             degenerate-policy suite: does a scenario measure driving?
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections import Counter
from pathlib import Path

EVENT_KEYS = (
    "collision_vehicle", "collision_pedestrian", "collision_object",
    "off_road", "wrong_lane", "red_light", "goal_reached",
)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if not args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    from cosim.errors import CosimError

    try:
        return int(args.func(args) or 0)
    except CosimError as exc:
        # the project's one error root (cosim, agents and eval): the message names the
        # input and the fix; a multi-line one (a worker's traceback) goes to a log file
        lines = str(exc).strip().splitlines() or [type(exc).__name__]
        more = f" (details in {_write_log(str(exc))})" if len(lines) > 1 else ""
        print(f"cosim: error: {lines[0]}{more}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("cosim: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug: one line here, the traceback in a log file
        import traceback

        path = _write_log(traceback.format_exc())
        first = (str(exc).strip().splitlines() or [""])[0][:200]
        print(f"cosim: unexpected error {type(exc).__name__}: {first} (traceback in {path}; "
              "please report it)", file=sys.stderr)
        return 1


def _write_log(text: str) -> Path:
    """Write `text` to a fresh log file under the temp folder and return its path."""
    import datetime as dt
    import tempfile

    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    path = Path(tempfile.gettempdir()) / f"cosim-error-{stamp}-{os.getpid()}.log"
    path.write_text(f"cosim {' '.join(sys.argv[1:])}\n{text}")
    return path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cosim", description=__doc__.split("\n\n")[0])
    p.add_argument("-v", "--verbose", action="store_true", help="log library messages")
    sub = p.add_subparsers(metavar="COMMAND")

    s = sub.add_parser("scenarios", help="list the driving environments")
    s.set_defaults(func=cmd_scenarios)

    d = sub.add_parser("drive", help="drive ACs with the scripted controller and print events")
    _scenario_args(d, steps=300)
    d.add_argument("--policy", choices=["autopilot", "random"], default="autopilot")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.add_argument("--gui", action="store_true", help="watch it in sumo-gui (needs a display)")
    d.set_defaults(func=cmd_drive)

    v = sub.add_parser("view", help="write camera mosaics and GIFs of what the ACs see")
    _scenario_args(v, steps=200)
    v.add_argument("--policy", choices=["autopilot", "random"], default="autopilot")
    v.add_argument("--out", type=Path, default=Path("view"), help="output folder")
    v.add_argument("--image-size", type=_int_in(8, 512), default=84, help="camera pixels (8-512)")
    v.add_argument("--moments", type=_int_in(1), default=3, help="mosaics taken along the run")
    v.add_argument("--extent", type=float, default=100.0,
                   help="metres across the top-down view beside the mosaic")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    v.set_defaults(func=cmd_view)

    n = sub.add_parser("nets", help="build or check the SUMO networks")
    n.add_argument("action", choices=["build", "check"])
    n.add_argument("--config", type=Path, action="append",
                   help="a netconvert .netccfg (default: every bundled network)")
    n.set_defaults(func=cmd_nets)

    from agents.registry import ALGORITHMS, DISCRETE  # the catalogue (no algorithm imported)

    t = sub.add_parser("train", help="train N ACs of one algorithm together (or --algo all)")
    t.add_argument("--algo", default="ppo",
                   help=f"{', '.join(ALGORITHMS)}, or all (every one, in parallel where CPUs allow)")
    t.add_argument("--env", default="env_1", help="env_1..env_5 or a scenario .yaml")
    t.add_argument("--agents", type=int, default=None, help="learning cars (default: from the preset)")
    t.add_argument("--steps", type=int, default=None, help="environment steps (default: from the preset)")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--preset", default="quick", help="smoke, quick or paper")
    t.add_argument("--action-type", choices=["discrete", "continuous"], default=None,
                   help=f"must match the algorithm (discrete: {' '.join(DISCRETE)})")
    t.add_argument("--agent-preset", default=None, help="hyperparameters: default or paper")
    t.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", dest="hyper",
                   help="change one agent hyperparameter, e.g. --set learning_rate=3e-4 (repeatable)")
    t.add_argument("--out", type=Path, default=Path("runs"), help="folder for run folders")
    t.add_argument("--resume", type=Path, default=None, metavar="RUN_DIR",
                   help="continue an interrupted run from its last checkpoint")
    t.add_argument("--envs", type=int, default=1,
                   help="environments stepped together, one process each when > 1 (ppo dqn ddpg td3)")
    t.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="torch device of the learners (auto: cuda when available)")
    t.add_argument("--torch-threads", type=int, default=0, metavar="K",
                   help="torch threads in the trainer (0: the CPUs the env workers leave, or torch's default)")
    t.add_argument("--pbt", type=_int_in(2), default=None, metavar="P",
                   help="Population Based Training on Ray Tune with P trials (eval/pbt.py)")
    t.add_argument("--pbt-interval", type=_int_in(1), default=None, metavar="STEPS",
                   help="environment steps between PBT exploit/explore decisions (default: the "
                        "preset's checkpoint interval)")
    t.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="with --pbt: an existing Ray cluster (default: local Ray)")
    t.add_argument("--quiet", action="store_true", help="plain log lines instead of a progress bar")
    t.set_defaults(func=cmd_train)
    e = sub.add_parser("test", help="the test protocol: Scenario 1 (together) and 2 (alone), report")
    e.add_argument("--agents", type=int, default=6,
                   help="ACs in Scenario 1, one per algorithm in the order ppo a3c impala dqn ddpg td3")
    e.add_argument("--envs", nargs="+", default=["env_1", "env_2", "env_3", "env_4", "env_5"])
    e.add_argument("--scenario", choices=["1", "2", "both"], default="both")
    e.add_argument("--episodes", type=_int_in(1), default=3, help="episodes per environment and scenario")
    e.add_argument("--steps", type=_int_in(1), default=500, help="steps per episode")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--policy", choices=["trained", "autopilot", "random"], default="trained",
                   help="trained checkpoints from --runs, or a reference driver")
    e.add_argument("--runs", type=Path, default=Path("runs"), help="where `cosim train` wrote runs")
    e.add_argument("--checkpoint", action="append", default=[], metavar="ALGO=PATH",
                   help="the checkpoint of one algorithm's AC instead of the newest under --runs "
                        "(repeatable), e.g. --checkpoint ppo=runs/x/checkpoints/ac_0/best.pt")
    e.add_argument("--out", type=Path, default=Path("reports"), help="report folder")
    e.add_argument("--references", default="all",
                   help="reference rows added to the report: 'all' (autopilot, random and the "
                        "degenerate suite of `cosim check-scenarios`), 'none', or a comma list")
    e.add_argument("--cross-play", action="store_true",
                   help="also the cross-play matrix: each algorithm's AC among ACs of each other "
                        "algorithm and among autopilots (eval/robustness.py)")
    e.add_argument("--cross-play-group", type=_int_in(2, 6), default=3, metavar="N",
                   help="ACs per cross-play episode: the ego and N-1 partners (default 3)")
    e.add_argument("--sweep", action="append", default=[], metavar="KIND=L1,L2",
                   help="also a robustness sweep (repeatable): density=0.5,1,2, camera_noise=0,0.05, "
                        "action_noise=0,0.2, dropout=0,0.3")
    e.add_argument("--no-replays", action="store_true",
                   help="skip the failure replays (clips and SUMO state of each first collision)")
    e.add_argument("--quiet", action="store_true")
    e.set_defaults(func=cmd_test)

    _benchmark_parser(sub)

    rp = sub.add_parser("replay", help="reopen a failure replay's SUMO state (from a cosim test report)")
    rp.add_argument("state", type=Path, help="replays/<...>/state.json (or state.xml) of a report")
    rp.add_argument("--plot", type=Path, default=None, metavar="PNG",
                    help="also draw the reloaded positions into this PNG")
    rp.set_defaults(func=cmd_replay)

    c = sub.add_parser("check-scenarios",
                       help="run the degenerate-policy suite: does a scenario measure driving?")
    c.add_argument("scenarios", nargs="*", default=["env_1", "env_2", "env_3", "env_4", "env_5"],
                   help="env_1..env_5 or scenario .yaml files (default: the five)")
    c.add_argument("--agents", type=int, nargs="+", default=[3, 6], help="AC counts to check")
    c.add_argument("--episodes", type=int, default=5, help="held-out episodes per policy")
    c.add_argument("--steps", type=int, default=None, help="steps per episode (default: horizon)")
    c.add_argument("--out", type=Path, default=None, help="also write the per-episode rows (CSV)")
    c.set_defaults(func=cmd_check_scenarios)
    return p


def _benchmark_parser(sub) -> None:
    from agents.registry import ALGORITHMS

    b = sub.add_parser("benchmark", help="train every (algorithm, environment, seed) as a Ray Tune "
                                         "trial, then test them and write the report")
    b.add_argument("--preset", choices=["smoke", "quick", "paper"], default="smoke")
    b.add_argument("--envs", nargs="+", default=["env_1", "env_2", "env_3", "env_4", "env_5"])
    b.add_argument("--algos", nargs="+", default=list(ALGORITHMS))
    b.add_argument("--seeds", type=_int_in(1), default=1, help="seeds 0..K-1 per cell")
    b.add_argument("--steps", type=_int_in(1), default=None,
                   help="environment steps per trial (default: the preset's)")
    b.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="an existing Ray cluster (HOST:PORT of `ray start --head`); default: local Ray")
    b.add_argument("--concurrent", type=_int_in(1), default=None, metavar="N",
                   help="trials at once (default: the CPUs here, or unlimited on a cluster)")
    b.add_argument("--gpus-per-trial", type=float, default=0.0, help="GPU share of each trial")
    b.add_argument("--no-ray", action="store_true",
                   help="train the same grid one trial after another in this process")
    b.add_argument("--train-only", action="store_true", help="train the grid, skip the test and report")
    b.add_argument("--out", type=Path, default=Path("benchmark"), help="benchmark folder")
    b.add_argument("--resume", action="store_true",
                   help="continue an interrupted benchmark in --out without redoing finished trials")
    b.add_argument("--quiet", action="store_true")
    b.set_defaults(func=cmd_benchmark)


def _scenario_args(p: argparse.ArgumentParser, steps: int) -> None:
    p.add_argument("scenario", nargs="?", default="env_3", help="env_1..env_5 or a scenario .yaml")
    p.add_argument("--agents", type=_int_in(1, 6), default=None,
                   help="learning cars (default: every spawn point of the scenario)")
    p.add_argument("--steps", type=_int_in(1), default=steps)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-background", action="store_true", help="no background cars")
    p.add_argument("--no-pedestrians", action="store_true", help="no pedestrians")


def _int_in(low: int, high: int | None = None):
    """An argparse type: an int in [low, high]; the error names the value and the range."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < low or (high is not None and value > high):
            span = f"{low}..{high}" if high is not None else f">= {low}"
            raise argparse.ArgumentTypeError(f"must be {span}, got {value}")
        return value

    return parse


def _output_folder(path: Path, flag: str) -> Path:
    """Create `path` (a folder for results) now, so a bad --out fails before any work."""
    from cosim.errors import OptionError
    from eval.runfolder import unwritable_reason

    reason = unwritable_reason(path)
    if reason:
        raise OptionError(f"{flag} {path}: cannot write there ({reason}); choose another {flag}")
    return path


# -- commands -----------------------------------------------------------------
def cmd_scenarios(args) -> int:
    from cosim.scenario import available_scenarios, load_scenario

    for name in available_scenarios():
        sc = load_scenario(name)
        peds = "pedestrians" if sc.pedestrians else "no pedestrians"
        print(f"{name:7s} {sc.title:11s} {sc.max_agents} ACs, {peds:14s} {sc.description}")
    return 0


def cmd_drive(args) -> int:
    import numpy as np
    from tqdm import tqdm

    from cosim.controller import Autopilot
    from cosim.world import World

    rng = np.random.default_rng(args.seed)
    counts: Counter = Counter()
    with World(args.scenario, args.agents, background=not args.no_background,
               pedestrians=not args.no_pedestrians,
               backend="gui" if args.gui else "auto") as world:
        world.reset(seed=args.seed)
        sc = world.scenario
        print(f"{sc.name} ({sc.title}): {world.num_acs} ACs, {args.steps} steps of {sc.dt} s, "
              f"seed {args.seed}, policy {args.policy}")
        pilots = {a: Autopilot(world, a) for a in world.ac_ids}
        final = {}
        bar = tqdm(range(args.steps), disable=args.quiet, unit="step", desc=sc.name)
        for step in bar:
            if not world.active:
                break
            if args.policy == "autopilot":
                controls = {a: tuple(pilots[a].act()) for a in world.active}
            else:
                controls = {a: tuple(rng.uniform(-1, 1, 2)) for a in world.active}
            for ac, res in world.step(controls).items():
                final[ac] = (step + 1, res.events.distance_to_goal,
                             _outcome(res.events.goal_reached, res.terminated, res.truncated))
                for key in EVENT_KEYS:
                    if getattr(res.events, key):
                        counts[(ac, key)] += 1
                        if key != "goal_reached" and counts[(ac, key)] == 1:
                            bar.write(f"  t={world.bridge.time:6.1f}s {ac}: {key}"
                                      + (f" ({res.events.hit})" if res.events.hit else ""))
        bar.close()
    _print_summary(world.ac_ids, final, counts)
    return 0


def _outcome(goal: bool, terminated: bool, truncated: bool) -> str:
    return "goal" if goal else "ended" if terminated else "truncated" if truncated else "running"


def _print_summary(ac_ids, final, counts) -> None:
    """`final`: AC -> (steps, metres to goal, outcome); `counts`: (AC, event) -> steps."""
    cols = ["vehicle", "pedestrian", "object", "off-road", "wrong lane", "red light"]
    print(f"\n{'AC':6s} {'steps':>5s} " + " ".join(f"{c:>10s}" for c in cols)
          + f" {'to goal m':>9s}  outcome")
    for ac in ac_ids:
        if ac not in final:
            continue
        steps, to_goal, outcome = final[ac]
        row = [counts[(ac, k)] for k in EVENT_KEYS[:6]]
        print(f"{ac:6s} {steps:5d} " + " ".join(f"{v:10d}" for v in row)
              + f" {to_goal:9.1f}  {outcome}")
    print("(event columns count the steps with that event)")


def cmd_view(args) -> int:
    import numpy as np
    from tqdm import tqdm

    from cosim.controller import Autopilot
    from cosim.env import CosimParallelEnv
    from cosim.viz import mosaic, save_gif, save_png, side_by_side

    _output_folder(args.out, "--out")
    env = CosimParallelEnv(
        args.scenario, num_agents=args.agents, action_types="continuous", seed=args.seed,
        image_size=args.image_size, background=not args.no_background,
        pedestrians=not args.no_pedestrians, terminate_on_collision=False,
        render_mode="rgb_array",
    )
    counts: Counter = Counter()
    final = {}
    rng = np.random.default_rng(args.seed)
    try:
        obs, _ = env.reset(seed=args.seed)
        world = env.world
        pilots = {a: Autopilot(world, a) for a in world.ac_ids}
        moments = set(np.linspace(0, args.steps - 1, args.moments).astype(int).tolist())
        first = env.possible_agents[0]
        cam_frames, overview_frames, written = [], [], []
        last = dict(obs)
        for step in tqdm(range(args.steps), disable=args.quiet, unit="step", desc="view"):
            if not env.agents:
                break
            if args.policy == "autopilot":
                actions = {a: pilots[a].act() for a in env.agents}
            else:
                actions = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents}
            obs, _, terms, truncs, infos = env.step(actions)
            last.update(obs)
            for ac, info in infos.items():
                final[ac] = (step + 1, info["distance_to_goal"],
                             _outcome(info["goal_reached"], terms[ac], truncs[ac]))
                for key in EVENT_KEYS:
                    if info[key]:
                        counts[(ac, key)] += 1
            if first in obs:
                cam_frames.append(obs[first])
            if step % 2 == 0:
                overview_frames.append(env.render())
            if step in moments:
                cams = mosaic([last[a] for a in env.possible_agents], cols=3, scale=2)
                # a close top-down view of the feature, as tall as the camera mosaic
                top = env.mirror.overview((cams.shape[0], cams.shape[0]), extent=args.extent)
                written.append(save_png(args.out / f"mosaic_{step:04d}.png",
                                        side_by_side(cams, top)))
        written.append(save_gif(args.out / f"camera_{first}.gif",
                                [np.kron(f, np.ones((3, 3, 1), np.uint8)) for f in cam_frames]))
        written.append(save_gif(args.out / "overview.gif", overview_frames, fps=5))
    finally:
        env.close()
    _print_summary(env.possible_agents, final, counts)
    print("\nwrote:\n" + "\n".join(f"  {p}" for p in written))
    return 0


def cmd_train(args) -> int:
    import os
    import subprocess

    from eval.train import ALGORITHMS, ASYNC_ALGOS, TrainError, make_config, parse_set, train

    if args.pbt is not None or (args.resume is not None and (args.resume / "pbt.json").exists()):
        return _train_pbt(args)
    try:
        if args.resume is not None:
            run = train(None, resume=args.resume, quiet=args.quiet)
            print(f"run folder: {run}")
            return 0
        algos = list(ALGORITHMS) if args.algo == "all" else [args.algo]
        hyper = parse_set(args.hyper)
        configs = [
            make_config(a, args.env, args.preset, agents=args.agents, steps=args.steps,
                        seed=args.seed, action_type=args.action_type, agent_preset=args.agent_preset,
                        hyper=hyper, envs=1 if a in ASYNC_ALGOS and args.algo == "all" else args.envs,
                        device=args.device,
                        torch_threads=args.torch_threads)
            for a in algos
        ]
    except TrainError as exc:
        print(f"cosim train: error: {exc}", file=sys.stderr)
        return 2
    if len(configs) == 1:
        try:
            run = train(configs[0], args.out, quiet=args.quiet)
        except TrainError as exc:
            print(f"cosim train: error: {exc}", file=sys.stderr)
            return 2
        print(f"run folder: {run}")
        return 0
    # --algo all: one process per algorithm, as many at once as there are CPUs
    parallel = max(1, os.cpu_count() or 1)
    print(f"training {len(configs)} algorithms, {parallel} at a time")
    pending = list(algos)
    running: dict[str, subprocess.Popen] = {}
    failed = []
    base = [sys.executable, "-m", "cosim.cli", "train", "--env", args.env, "--preset", args.preset,
            "--seed", str(args.seed), "--out", str(args.out), "--quiet", "--device", args.device,
            "--torch-threads", str(args.torch_threads)]
    if args.agents is not None:
        base += ["--agents", str(args.agents)]
    if args.steps is not None:
        base += ["--steps", str(args.steps)]
    if args.agent_preset is not None:
        base += ["--agent-preset", args.agent_preset]
    for item in args.hyper:
        base += ["--set", item]
    try:
        while pending or running:
            while pending and len(running) < parallel:
                algo = pending.pop(0)
                envs = [] if algo in ASYNC_ALGOS else ["--envs", str(args.envs)]
                running[algo] = subprocess.Popen(base + envs + ["--algo", algo])
            for algo, proc in list(running.items()):
                try:
                    proc.wait(timeout=0.5)
                except subprocess.TimeoutExpired:
                    continue
                del running[algo]
                ok = proc.returncode == 0
                print(f"{algo}: {'done' if ok else f'FAILED (exit {proc.returncode})'}", flush=True)
                if not ok:
                    failed.append(algo)
    finally:
        for proc in running.values():
            proc.terminate()
    return 1 if failed else 0


def _train_pbt(args) -> int:
    from eval.pbt import run_pbt
    from eval.raysession import ray_available
    from eval.train import TrainError, make_config, parse_set

    if not ray_available():
        print("cosim train: error: --pbt needs Ray Tune, which is not installed; install it with: "
              "pip install -e '.[tune]'", file=sys.stderr)
        return 2
    try:
        cfg = None
        if args.resume is None:
            if args.algo == "all":
                raise TrainError("--pbt trains one algorithm; choose it with --algo")
            cfg = make_config(args.algo, args.env, args.preset, agents=args.agents, steps=args.steps,
                              seed=args.seed, action_type=args.action_type,
                              agent_preset=args.agent_preset, hyper=parse_set(args.hyper),
                              envs=args.envs, device=args.device, torch_threads=args.torch_threads or 1)
        folder = run_pbt(cfg, args.pbt or 0, args.pbt_interval, args.out, resume=args.resume,
                         address=args.ray_address)
    except TrainError as exc:
        print(f"cosim train: error: {exc}", file=sys.stderr)
        return 2
    print(f"lineage: {folder / 'lineage.csv'}  {folder / 'lineage.png'}")
    print(f"run folder (best trial): {folder}")
    return 0


def cmd_test(args) -> int:
    import datetime as dt

    from tqdm import tqdm

    from eval.protocol import (
        ALGO_ORDER,
        ProtocolError,
        ProtocolPlan,
        find_checkpoints,
        policy_factory,
        run_protocol,
    )

    if not 1 <= args.agents <= 6:
        print("cosim test: error: --agents must be 1..6 (one AC per algorithm)", file=sys.stderr)
        return 2
    from eval.protocol import reference_rows
    from eval.validity import POLICIES

    refs_wanted = (list(POLICIES) if args.references == "all" else []
                   if args.references == "none" else args.references.split(","))
    unknown = sorted(set(refs_wanted) - set(POLICIES))
    if unknown:
        print(f"cosim test: error: --references {','.join(unknown)}: unknown; valid: all, none, "
              f"or a comma list of {', '.join(POLICIES)}", file=sys.stderr)
        return 2
    scenarios = (1, 2) if args.scenario == "both" else (int(args.scenario),)
    plan = ProtocolPlan(envs=tuple(args.envs), scenarios=scenarios, episodes=args.episodes,
                    steps=args.steps, seed=args.seed, agents=args.agents)
    algos = list(ALGO_ORDER[: args.agents])
    try:
        from eval.robustness import parse_sweeps

        sweeps = parse_sweeps(args.sweep)
        given = _checkpoint_slots(args.checkpoint, algos)
        if given and args.policy != "trained":
            raise ProtocolError(f"--checkpoint is for --policy trained, not --policy {args.policy}")
        ckpts = None
        if args.policy == "trained":
            ckpts = {**find_checkpoints(args.runs, [a for a in algos if a not in given]), **given}
            ckpts = {a: ckpts[a] for a in algos}
        factory = policy_factory(args.policy, ckpts)
    except ProtocolError as exc:
        print(f"cosim test: error: {exc}", file=sys.stderr)
        return 2
    from cosim.scenario import load_scenario

    for env_name in plan.envs:  # a bad name fails now, not after the first environments ran
        load_scenario(env_name)
    out = _output_folder(args.out / dt.datetime.now().strftime("%Y%m%d-%H%M%S"), "--out")
    for algo, path in (ckpts or {}).items():
        print(f"{algo:7s} {path}")
    from eval import selection
    from eval.report import provenance, write_paper_report

    # provenance first: the code, checkpoints and hashes as they are when the test starts
    picked = {a: selection.describe(p) if a in given else
              (selection.choose(p.parent.parent.parent) or selection.describe(p))
              for a, p in (ckpts or {}).items()}
    prov = provenance(policy=args.policy, plan=plan, algos=algos, checkpoints=ckpts,
                      selections=picked, command=_test_command(args))
    units = len(plan.envs) * ((1 in scenarios) + (2 in scenarios) * len(algos))
    bar = tqdm(total=units, disable=args.quiet, unit="run", desc="test")
    records = run_protocol(plan, factory, algos, progress=lambda name: bar.update(1))
    bar.close()
    refs = None
    if refs_wanted:
        refs = reference_rows(plan, refs_wanted)
    replays = []
    if not args.no_replays:
        from eval import replay

        labels = {t["algorithm"]: t["label"] for t in prov["tested"]}
        replays = replay.capture(plan, factory, algos, records, out, labels)
    extra_md = ""
    if args.cross_play or sweeps:
        from eval import robustness

        labels = {t["algorithm"]: t["label"] for t in prov["tested"]}
        cross = (robustness.run_cross_play(plan, factory, algos, group=args.cross_play_group)
                 if args.cross_play else None)
        swept = {kind: robustness.run_sweep(plan, factory, algos, kind, levels)
                 for kind, levels in sweeps.items()}
        _, extra_md = robustness.write(out, labels, cross, swept)
    written = write_paper_report(records, out, prov=prov, references=refs, replays=replays,
                                 extra_md=extra_md)
    print((out / "rq1.md").read_text())
    print(f"index: {out / 'index.html'}")
    print("wrote:\n" + "\n".join(f"  {p}" for p in written))
    return 0


def cmd_benchmark(args) -> int:
    import time

    from eval.benchmark import BenchmarkPlan, run_ray, run_sequential, write_report
    from eval.raysession import INSTALL_HINT, ray_available

    if not args.no_ray and not ray_available():
        print(f"cosim benchmark: error: {INSTALL_HINT}", file=sys.stderr)
        return 2
    plan = BenchmarkPlan(preset=args.preset, envs=tuple(args.envs), algos=tuple(args.algos),
                         seeds=args.seeds, steps=args.steps)
    cells = plan.cells()  # a bad environment or algorithm fails here, before Ray starts
    _output_folder(args.out, "--out")
    say = (lambda text: None) if args.quiet else (lambda text: print(text, flush=True))
    start = time.monotonic()
    say(f"benchmark {args.preset}: {len(cells)} trials -> {args.out}")
    if args.no_ray:
        runs = run_sequential(plan, args.out, resume=args.resume, progress=lambda n: say(f"trained {n}"))
    else:
        concurrent = args.concurrent or (0 if args.ray_address else (os.cpu_count() or 1))
        runs = run_ray(plan, args.out, resume=args.resume, address=args.ray_address,
                       concurrent=concurrent, gpus_per_trial=args.gpus_per_trial)
    say(f"trained {len(runs)} trials in {time.monotonic() - start:.0f} s: {args.out / 'runs'}")
    if args.train_only:
        return 0
    written = write_report(plan, args.out, command=["benchmark", *sys.argv[2:]],
                           progress=lambda n: say(f"tested {n}"))
    say(f"report: {args.out / 'report' / 'index.html'} ({len(written)} files, "
        f"{time.monotonic() - start:.0f} s in all)")
    return 0


def cmd_replay(args) -> int:
    from eval import replay

    path = args.state
    if not path.exists() or not path.with_suffix(".json").exists():
        print(f"cosim replay: error: {path}: not a failure replay (give the state.json of a "
              "report's replays/ folder)", file=sys.stderr)
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


def _test_command(args) -> list[str]:
    """The `cosim test` command line the parsed options stand for (for the report)."""
    cmd = ["test", "--agents", str(args.agents), "--envs", *args.envs, "--scenario", args.scenario,
           "--episodes", str(args.episodes), "--steps", str(args.steps), "--seed", str(args.seed),
           "--policy", args.policy]
    if args.policy == "trained":
        cmd += ["--runs", str(args.runs)]
    for item in args.checkpoint:
        cmd += ["--checkpoint", item]
    cmd += ["--no-replays"] if args.no_replays else []
    if args.cross_play:
        cmd += ["--cross-play", "--cross-play-group", str(args.cross_play_group)]
    for item in args.sweep:
        cmd += ["--sweep", item]
    return cmd + ["--references", args.references, "--out", str(args.out)]


def cmd_check_scenarios(args) -> int:
    from tqdm import tqdm

    from cosim.errors import CosimError
    from cosim.scenario import load_scenario
    from eval import validity

    if args.episodes < 1 or (args.steps is not None and args.steps < 1):
        raise CosimError("--episodes and --steps must be >= 1")
    scenarios = [load_scenario(s) for s in args.scenarios]  # fail on a bad name before running
    for sc in scenarios:
        if any(not 1 <= n <= sc.max_agents for n in args.agents):
            raise CosimError(f"--agents {args.agents}: scenario {sc.name!r} has 1..{sc.max_agents} "
                             "spawn points; pass counts in that range")
    failed, frames = [], []
    for sc in scenarios:
        for n in args.agents:
            bar = tqdm(total=len(validity.POLICIES), desc=f"{sc.name} x{n}", leave=False,
                       disable=None)
            rows = validity.check_scenario(
                sc, n, args.episodes, args.steps,
                progress=lambda p, bar=bar: (bar.set_postfix_str(p), bar.update(0)),
            )
            bar.close()
            table = validity.summarize(rows)
            problems = validity.failures(table)
            title = f"{sc.name} ({sc.title or sc.description}), {n} ACs, {args.episodes} episodes"
            print(f"\n### {title}\n\n{validity.format_table(table)}\n")
            print("valid" if not problems else "NOT VALID:\n  " + "\n  ".join(problems))
            failed += [f"{sc.name} x{n}: {p}" for p in problems]
            frames.append(rows.assign(scenario=sc.name, agents=n))
    if args.out:
        import pandas as pd

        args.out.parent.mkdir(parents=True, exist_ok=True)
        pd.concat(frames).to_csv(args.out, index=False)
        print(f"wrote {args.out}")
    if failed:
        print(f"\n{len(failed)} validity criteria failed", file=sys.stderr)
        return 1
    print("\nevery scenario passed the validity criteria")
    return 0


def _checkpoint_slots(items: list[str], algos: list[str]) -> dict[str, Path]:
    """``["ppo=path.pt", ...]`` (``--checkpoint``) -> ``{"ppo": Path("path.pt")}``."""
    from eval.protocol import ProtocolError

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


def cmd_nets(args) -> int:
    from cosim import nets

    configs = args.config or nets.default_configs()
    if args.action == "build":
        for cfg in configs:
            out = nets.build(cfg)
            print(f"built {out}")
        return 0
    nets.check(configs)
    print(f"up to date: {', '.join(str(c) for c in configs)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
