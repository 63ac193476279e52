"""`cosim benchmark`: the whole study in one command, each (algorithm, environment, seed)
a Ray Tune trial, then the test protocol on the trained policies and its report.

A benchmark folder (``--out``)::

    benchmark.json     the plan (preset, envs, algos, seeds) that --resume reads back
    tune/grid/         Ray Tune's experiment: trial results, and checkpoints that point at
                       the trial's run folder (a few bytes each: no copy of the run)
    trials/<cell>/     where a trial trains (a normal run folder inside; moved once finished)
    runs/<cell>/       the finished run folders, <env>__<algo>__<seed>__bench (what `cosim test` loads)
    report/            the `cosim test` report: Scenario 1 and 2 in every environment

A trial is the ordinary training run (:func:`eval.training.train.train`); it reports
``env_steps`` and ``mean_return`` (the mean episodic return over each AC's last 20
episodes) to Tune at every checkpoint. The run folder is resumable by itself
(eval/training/runfolder.py), so Tune's checkpoint holds only its path (``run_path.txt``) and a
restored trial continues with ``train(resume=...)`` from the folder's own last commit:
Tune never copies checkpoints (with several nodes, ``--out`` must be a path every node
reaches, as Tune's storage_path must). A finished run keeps what ``--keep`` says
(eval/training/runfolder.py KEEP_POLICIES; default ``best``: one policy file per AC). ``--no-ray`` trains the
same cells one after another in this process: same configs, same seeds, one torch
thread per trial in both cases, so PPO, DQN, DDPG and TD3 give the same weights
either way (A3C's learner threads apply their updates in no fixed order: with more
than one environment it is not bit-reproducible).
A finished cell is never trained again: ``--resume`` continues an interrupted
benchmark from each unfinished trial's last checkpoint, and ``--resume`` with a larger
``--seeds`` adds the new seeds to a finished benchmark (nothing else may change).
"""

from __future__ import annotations

import json
import logging
import random
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import CosimError
from eval.labels import ENVS
from eval.testing.validity import POLICIES
from eval.training.config import DEMO_ALGOS, DEMO_HYPER, DEMO_UPDATES, resolve
from eval.training.options import RunOptions, TrainError, benchmark_names, declared
from eval.training.train import ALGORITHMS, TrainConfig, train

log = logging.getLogger(__name__)



class BenchmarkError(CosimError, ValueError):
    """A benchmark request that cannot run; the message says what to change."""


@dataclass(frozen=True)
class TestSettings:
    """How the trained policies are tested (the `cosim test` options of a preset)."""

    episodes: int
    """Episodes per environment and scenario."""
    steps: int | None
    """Steps per test episode; None: the scenario's horizon (ProtocolPlan.steps)."""
    references: tuple[str, ...] = ()
    """Reference rows (eval/testing/validity.py POLICIES) added to the report."""


QUICK_REFERENCES = ("autopilot", "autopilot-discrete", "safe-non-turner", "random")
TEST_SETTINGS = {
    # the whole reference suite: the yardstick of Table RQ1 (seconds at 60 steps, no camera)
    "smoke": TestSettings(episodes=1, steps=60, references=POLICIES),
    # the two autopilots (the discrete one is a discrete learner's ceiling), the safe
    # non-turner (did it learn to turn?) and random (docs/task.md, "Reference policies")
    "quick": TestSettings(episodes=3, steps=None, references=QUICK_REFERENCES),
    # the scenarios' horizon and the whole reference suite of `cosim check-scenarios`
    "standard": TestSettings(episodes=5, steps=None, references=POLICIES),
    "paper": TestSettings(episodes=3, steps=None, references=QUICK_REFERENCES),
}


SAVED_ALWAYS = ("preset", "steps", "collisions", "fault")
"""Run options benchmark.json always holds; the others only when set, so a plan saved before
they existed still reads back as equal (the grid is resumed only with the options it started with)."""


@dataclass(frozen=True, init=False)
class BenchmarkPlan:
    """The grid: every (algorithm, environment, seed), and the run options every trial takes.

    Built as ``BenchmarkPlan(envs=..., algos=..., seeds=..., preset=..., steps=..., ...)``: the
    keywords beside the grid's are the run options `cosim benchmark` takes (those declared
    ``benchmark`` in eval/training/options.py, :func:`~eval.training.options.benchmark_names`),
    with the benchmark's defaults (preset ``standard``); or with ``options``, a RunOptions.
    ``plan.preset``, ``plan.steps``, ...: those options. ``collisions=None`` is what a plan saved
    before 2026-11-24 holds: it meant, and still means, "end".

    Raises:
        BenchmarkError: an algorithm, seed count or option the grid cannot take, naming the flag.
    """

    envs: tuple[str, ...]
    """The environments of the grid (``--envs``)."""
    algos: tuple[str, ...]
    """The algorithms of the grid (``--algos``)."""
    seeds: int
    """How many seeds per (algorithm, environment): ``first_seed`` .. ``first_seed + seeds - 1``."""
    first_seed: int
    """The first seed (``--first-seed``): a benchmark of seed 1 alone trains exactly the cells
    "seed 1" of a benchmark of seeds 0..2, so a long grid can run in parts (sessions, machines)
    and each part's results join the others' (studies/science.py ``--combine``)."""
    options: RunOptions
    """The run options of every trial (the benchmark's; the others at their defaults): trial
    (algo, env, seed) trains ``options.for_algo(algo)`` there with one torch thread; with
    ``demo_steps`` the DQN, DDPG and TD3 trials are the demonstration variant (pre-training
    :data:`~eval.training.config.DEMO_UPDATES` steps, :data:`~eval.training.config.DEMO_HYPER`),
    the others the plain grid's."""

    def __init__(self, envs: Sequence[str] = ENVS, algos: Sequence[str] = ALGORITHMS, seeds: int = 1,
                 first_seed: int = 0, options: RunOptions | None = None, **run: Any):
        for name, value in (("envs", tuple(envs)), ("algos", tuple(algos)), ("seeds", seeds),
                            ("first_seed", first_seed), ("options", options or _benchmark_options(run))):
            object.__setattr__(self, name, value)
        if options is not None and run:
            raise BenchmarkError(f"give the run options as options= or as keywords, not both ({', '.join(run)})")
        taken = benchmark_names()
        others = {n: v for n, v in self.options.changed().items() if n not in taken}
        if others:
            raise BenchmarkError(f"{', '.join(others)}: not an option of `cosim benchmark` (it takes "
                                 f"{', '.join(taken)}; eval/training/options.py declares which)")
        unknown = sorted(set(self.algos) - set(ALGORITHMS))
        if unknown or not self.algos:
            raise BenchmarkError(f"--algos {' '.join(unknown) or '(none)'}: choose from {' '.join(ALGORITHMS)}")
        if self.seeds < 1:
            raise BenchmarkError(f"--seeds must be >= 1, got {self.seeds}")
        if self.first_seed < 0:
            raise BenchmarkError(f"--first-seed must be >= 0, got {self.first_seed}")
        if not self.envs:
            raise BenchmarkError("--envs: name at least one environment")

    def __getattr__(self, name: str) -> Any:  # plan.preset, plan.steps, ...: the trials' run options
        if name in benchmark_names():
            return getattr(self.options, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @property
    def seed_list(self) -> range:
        """The seeds of every (algorithm, environment), in order."""
        return range(self.first_seed, self.first_seed + self.seeds)

    def trial(self, algo: str, env: str, seed: int) -> RunOptions:
        """The run options of trial (``algo``, ``env``, ``seed``)."""
        demos = bool(self.options.demo_steps) and algo in DEMO_ALGOS
        return self.options.for_algo(algo).replace(
            env=env, seed=seed, torch_threads=1, demo_steps=self.options.demo_steps if demos else 0,
            demo_updates=DEMO_UPDATES if demos else 0, hyper=DEMO_HYPER[algo] if demos else {})

    def cells(self) -> list[TrainConfig]:
        """One TrainConfig per trial, environment-major (the order --no-ray trains them)."""
        return [resolve(self.trial(algo, env, seed))
                for env in self.envs for algo in self.algos for seed in self.seed_list]

    def to_dict(self) -> dict[str, Any]:
        """The plan as benchmark.json holds it: the grid, the run options of :data:`SAVED_ALWAYS`
        and the others that are set, ``first_seed`` when not 0."""
        run = {n: getattr(self.options, n) for n in SAVED_ALWAYS}
        grid = {"envs": list(self.envs), "algos": list(self.algos), "seeds": self.seeds}
        extra = {"first_seed": self.first_seed} if self.first_seed else {}
        return {**run, **grid, **self.options.changed(benchmark_names()), **extra}


def _benchmark_options(run: dict[str, Any]) -> RunOptions:
    """The RunOptions of a benchmark's keywords (``steps=``, ``obs=``, ...), with the benchmark's
    defaults where it has its own (``--preset standard``)."""
    taken = benchmark_names()
    unknown = sorted(set(run) - set(taken))
    if unknown:
        raise BenchmarkError(f"{', '.join(unknown)}: not an option of `cosim benchmark` (it takes "
                             f"{', '.join(taken)}; eval/training/options.py declares which)")
    if "collisions" in run and run["collisions"] is None:  # a plan saved before the default changed
        run = {**run, "collisions": "end"}
    defaults = {n: spec.benchmark_default for n, spec in declared() if spec.benchmark_default is not None}
    try:
        return RunOptions(**{**defaults, **run})
    except TrainError as exc:
        raise BenchmarkError(str(exc)) from None


def saved_plan(path: Path) -> dict[str, Any]:
    """A benchmark.json as :meth:`BenchmarkPlan.to_dict` writes it today: a plan saved
    before collisions were recorded trained under the paper's rule ("end")."""
    return {"collisions": "end", **json.loads(Path(path).read_text())}


def cell_name(cfg: TrainConfig | dict) -> str:
    """``<env>__<algo>__<seed>__bench``: a run-folder name `cosim test --runs` recognises."""
    c = cfg if isinstance(cfg, dict) else cfg.to_dict()
    return f"{Path(c['env']).stem}__{c['algo']}__{c['seed']}__bench"


def trial_resources(cfg: TrainConfig, max_cpus: int | None = None, gpus: float = 0.0) -> dict:
    """CPUs a trial keeps busy: its env workers (every algorithm steps ``cfg.envs`` environments)."""
    cpus = cfg.envs
    if max_cpus:
        cpus = min(cpus, max_cpus)
    return {"cpu": cpus, "gpu": gpus}


def packed(cells: list[TrainConfig], max_cpus: int | None = None) -> list[TrainConfig]:
    """``cells`` in the order Tune should start them: those that keep fewer CPUs busy first
    (a stable sort, so the grid's order holds within each group). Tune starts trials in
    order and a trial that does not fit waits with every one behind it: on 2 cores a
    2-CPU A3C trial behind a 1-CPU PPO trial left a core idle for the whole PPO trial."""
    return sorted(cells, key=lambda c: trial_resources(c, max_cpus)["cpu"])


# -- one trial ---------------------------------------------------------------------------
def _seed_everything(seed: int) -> None:
    """Same global RNG state at the start of a trial, in a fresh Ray worker or in this process."""
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def train_cell(cfg: TrainConfig, folder: Path, restore_from: Path | None = None,
               on_checkpoint: Callable[[Path, int, float], None] | None = None,
               prepare: Callable[[Path], None] | None = None, keep: str = "all") -> Path:
    """Train one cell in ``folder`` (wiped first), from scratch or from a copied run folder
    (``prepare(run)`` edits the copy before it is resumed); ``keep``: what the finished run
    keeps (eval/training/runfolder.py KEEP_POLICIES).

    Returns:
        The run folder.
    """
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    _seed_everything(cfg.seed)
    if restore_from is None:
        return train(cfg, folder, quiet=True, progress=False, on_checkpoint=on_checkpoint, keep=keep)
    run = folder / "run"
    shutil.copytree(restore_from, run)
    if prepare is not None:
        prepare(run)
    return train(None, resume=run, quiet=True, progress=False, on_checkpoint=on_checkpoint, keep=keep)


def finite(value: float) -> float:
    """A score Tune can rank: -inf before the first finished episode."""
    return float(value) if np.isfinite(value) else float("-inf")


RUN_POINTER = "run_path.txt"
"""The one file of a grid trial's Tune checkpoint: the absolute path of its run folder."""
TRIAL_NODES = "trial_nodes.jsonl"
"""In a grid trial's run folder: one line per Ray worker that trained it (node IP and id,
host, PID, the env steps at its first checkpoint), appended at that worker's first checkpoint:
a trial retried on another node after its node died has two (docs/guide.md#scale-out-a-cluster-of-several-machines)."""
TRIAL_RETRIES = 2
"""Tune's FailureConfig(max_failures): a trial whose worker or node dies starts again from
its last checkpoint (a resumable run folder) up to this many times before it counts as failed."""


def _record_node(run: Path, env_steps: int) -> None:
    """Append this Ray worker's node to ``run/TRIAL_NODES``."""
    import os
    import socket

    import ray

    ctx = ray.get_runtime_context()
    line = {"node_ip": ray.util.get_node_ip_address(), "node_id": ctx.get_node_id(),
            "hostname": socket.gethostname(), "pid": os.getpid(), "env_steps": int(env_steps)}
    with open(Path(run) / TRIAL_NODES, "a") as f:
        f.write(json.dumps(line) + "\n")


def run_of_checkpoint(checkpoint) -> Path:
    """The run folder a grid trial's Tune checkpoint points at."""
    with checkpoint.as_directory() as restored:
        return Path((Path(restored) / RUN_POINTER).read_text().strip())


def _tune_trial(config: dict) -> None:
    """Ray Tune function trainable: one cell, reporting at every checkpoint.

    The checkpoint Tune keeps is a pointer to the run folder, which is resumable by
    itself (module docstring): a restored trial resumes that folder in place."""
    import tempfile

    from ray import tune

    cfg = TrainConfig(**config["cell"])
    folder = Path(config["scratch"]) / cell_name(cfg)
    keep = config.get("keep", "best")
    recorded = []

    def report(run: Path, env_steps: int, mean_return: float) -> None:
        if not recorded:  # which node trains it (a retry after a node died may be elsewhere)
            _record_node(run, env_steps)
            recorded.append(env_steps)
        with tempfile.TemporaryDirectory() as tmp:  # tune.report persists it before returning
            (Path(tmp) / RUN_POINTER).write_text(str(Path(run).resolve()))
            tune.report({"env_steps": env_steps, "mean_return": finite(mean_return)},
                        checkpoint=tune.Checkpoint.from_directory(tmp))

    checkpoint = tune.get_checkpoint()
    run = run_of_checkpoint(checkpoint) if checkpoint is not None else None
    if run is None or not (run / "config.yaml").exists():
        run = earlier_run(folder, cfg)  # a grid started anew over the same trials/ folder
        done = steps_done(run) if run is not None else 0
        if done >= cfg.steps:
            report(run, done, float("nan"))  # finished before: Tune only records it
            return
    if run is not None:
        _seed_everything(cfg.seed)
        train(None, resume=run, quiet=True, progress=False, on_checkpoint=report, keep=keep)
    else:
        train_cell(cfg, folder, None, report, keep=keep)


def earlier_run(folder: Path, cfg: TrainConfig) -> Path | None:
    """The newest run folder under ``folder`` (a trial's ``trials/<cell>``) that trained
    exactly ``cfg`` (its config.yaml, compared through JSON) and committed a checkpoint
    (state.json), else None. A grid started anew over an interrupted one (Tune's state lost
    or deleted, say after a preset changed: docs/guide.md) continues such runs instead of
    wiping them; a run of another config is trained again from scratch."""
    from eval.training.runfolder import load_run_config

    want = json.loads(json.dumps(cfg.to_dict()))
    for run in sorted(Path(folder).glob("*"), reverse=True):
        if not (run / "state.json").exists() or not (run / "config.yaml").exists():
            continue
        try:
            ran = json.loads(json.dumps(load_run_config(run).to_dict()))
        except CosimError:
            continue
        if ran == want:
            return run
    return None


# -- the grid ----------------------------------------------------------------------------
def _export(run: Path, dest: Path, move: bool = False) -> None:
    """Copy (or move) a finished run folder to ``runs/<cell>``, renamed into place last, so
    that ``runs/<cell>`` exists only complete."""
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    if move:
        shutil.move(run, tmp)
    else:
        shutil.copytree(run, tmp, ignore=shutil.ignore_patterns("run.lock"))
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)


def _prepare(plan: BenchmarkPlan, out: Path, resume: bool) -> bool:
    """Check ``out`` against the saved plan and save this one.

    Returns:
        True when ``--resume`` raises ``--seeds`` of a finished benchmark (the new seeds
        train; the finished cells stay), False otherwise.
    """
    out.mkdir(parents=True, exist_ok=True)
    saved = out / "benchmark.json"
    more_seeds = False
    if resume:
        if not saved.exists():
            raise BenchmarkError(f"--resume: {out} holds no benchmark (no benchmark.json); "
                                 "start one without --resume")
        old = saved_plan(saved)
        more_seeds = adds_seeds(old, plan)
        if old != plan.to_dict() and not more_seeds:
            raise BenchmarkError(f"--resume: {saved} was started with {old}; repeat those options "
                                 "(or drop --resume and choose another --out; only --seeds may grow)")
        if more_seeds:
            finished = finished_runs(plan, out)
            unfinished = [name for name in _saved_cells(old, plan) if name not in finished]
            if unfinished:
                raise BenchmarkError(f"--resume --seeds {plan.seeds}: {len(unfinished)} trial(s) of the "
                                     f"saved {old['seeds']}-seed benchmark are unfinished ({unfinished[0]}, ...); "
                                     f"finish them first with --resume --seeds {old['seeds']}")
    elif saved.exists():
        raise BenchmarkError(f"{out} already holds a benchmark; continue it with --resume or "
                             "choose another --out")
    saved.write_text(json.dumps(plan.to_dict(), indent=2))
    return more_seeds


def adds_seeds(old: dict, plan: BenchmarkPlan | dict) -> bool:
    """Whether ``plan`` (or its ``to_dict()``) is the saved plan ``old`` with more seeds and
    nothing else changed."""
    new = plan if isinstance(plan, dict) else plan.to_dict()
    return (isinstance(old.get("seeds"), int) and new["seeds"] > old["seeds"]
            and {**old, "seeds": new["seeds"]} == new)


def load_plan(out: Path) -> BenchmarkPlan:
    """The plan saved in ``out/benchmark.json``.

    Raises:
        BenchmarkError: ``out`` holds no benchmark.
    """
    saved = Path(out) / "benchmark.json"
    if not saved.exists():
        raise BenchmarkError(f"--out {out}: no benchmark.json there; name the folder a "
                             "`cosim benchmark` wrote (its --out)")
    return BenchmarkPlan(**{k: tuple(v) if isinstance(v, list) else v for k, v in saved_plan(saved).items()})


def steps_done(run: Path) -> int:
    """Env steps of a run folder's last committed checkpoint (0 before the first)."""
    state = Path(run) / "state.json"
    return int(json.loads(state.read_text()).get("env_steps", 0)) if state.exists() else 0


def finished_cells(plan: BenchmarkPlan, out: Path) -> list[str]:
    """Names of ``plan``'s cells that finished training in ``out``: the run is in ``runs/`` or,
    not yet moved (Tune moves them when the whole grid ends), in ``trials/<cell>`` at its budget."""
    done = []
    for cfg in plan.cells():
        name = cell_name(cfg)
        started = (Path(out) / "trials" / name).glob("*")
        if (Path(out) / "runs" / name).exists() or any(steps_done(r) >= cfg.steps for r in started):
            done.append(name)
    return done


def finished_count(out: Path) -> tuple[int, int]:
    """(finished, all) cells of the benchmark in ``out`` (:func:`finished_cells` of its saved plan)."""
    plan = load_plan(out)
    return len(finished_cells(plan, out)), len(plan.cells())


def finished_runs(plan: BenchmarkPlan, out: Path) -> dict[str, Path]:
    """Cell name -> run folder of every cell of ``plan`` whose run is in ``out/runs``
    (a cell's run is moved there only once it finished)."""
    names = (cell_name(c) for c in plan.cells())
    return {name: Path(out) / "runs" / name for name in names if (Path(out) / "runs" / name).exists()}


def _saved_cells(old: dict, plan: BenchmarkPlan) -> list[str]:
    """Cell names of the saved plan ``old`` (``plan`` with the saved seed count)."""
    return [cell_name(c) for c in plan.cells() if c.seed < plan.first_seed + old["seeds"]]


def run_sequential(plan: BenchmarkPlan, out: Path, resume: bool = False,
                   progress: Callable[[str], None] | None = None, keep: str = "best") -> dict[str, Path]:
    """Train every cell in this process, one after another (``--no-ray``).

    ``progress`` is called with each cell's name once it is trained (not for cells
    whose run was already in ``out/runs``); ``keep``: what a finished run keeps.

    Returns:
        Cell name -> finished run folder under ``out/runs``.
    """
    out = Path(out)
    _prepare(plan, out, resume)
    done = {}
    for cfg in plan.cells():
        name = cell_name(cfg)
        dest = out / "runs" / name
        if not dest.exists():
            folder = out / "trials" / name
            runs = sorted(p for p in folder.glob("*") if (p / "config.yaml").exists()) if resume else []
            if runs:  # interrupted: continue from its last checkpoint
                _seed_everything(cfg.seed)
                run = train(None, resume=runs[-1], quiet=True, progress=False, keep=keep)
            else:
                run = train_cell(cfg, folder, keep=keep)
            _export(run, dest, move=True)
            shutil.rmtree(folder, ignore_errors=True)
            if progress:
                progress(name)
        done[name] = dest
    return done


def run_ray(plan: BenchmarkPlan, out: Path, *, resume: bool = False, address: str | None = None,
            concurrent: int = 2, gpus_per_trial: float = 0.0, keep: str = "best",
            progress: Callable[[str], None] | None = None) -> dict[str, Path]:
    """Train every cell as a Ray Tune trial, ``concurrent`` at a time; ``keep``: what a
    finished run keeps (eval/training/runfolder.py KEEP_POLICIES); ``progress``: called with
    one line per trial as it ends (eval/scale/trial_lines.py; a restored grid too).

    Returns:
        Cell name -> finished run folder under ``out/runs``.

    Raises:
        BenchmarkError: a trial failed (naming it and its error) or the run was interrupted.
        eval.scale.raysession.RayError: Ray missing or the address does not answer.
    """
    import os

    from eval.scale.raysession import ray_session, refuse_old_layout

    out = Path(out).resolve()
    with ray_session(address):
        more_seeds = _prepare(plan, out, resume)
        from functools import partial

        from ray import tune

        from eval.scale.trial_lines import TrialLines

        cells = plan.cells()
        finished = finished_runs(plan, out)
        todo = [c for c in cells if cell_name(c) not in finished]
        if not todo:
            return finished
        local_cpus = None if address else (os.cpu_count() or 1)
        trainable = tune.with_resources(
            _tune_trial, lambda config: trial_resources(TrainConfig(**config["cell"]), local_cpus,
                                                        gpus_per_trial))
        path = out / "tune" / "grid"
        if more_seeds:  # the saved grid finished (its runs are exported): a new grid of the new seeds
            shutil.rmtree(path, ignore_errors=True)
        if resume and not more_seeds and tune.Tuner.can_restore(str(path)):
            refuse_old_layout(path)
            tuner = tune.Tuner.restore(str(path), trainable, resume_unfinished=True,
                                       resume_errored=True)
        else:
            tuner = tune.Tuner(
                trainable,
                param_space={"cell": tune.grid_search([c.to_dict() for c in packed(todo, local_cpus)]),
                             "scratch": str(out / "trials"), "keep": keep},
                # a finished trial's worker takes the next trial: no process start and torch
                # import per trial (each trial reseeds and sets its torch threads itself)
                tune_config=tune.TuneConfig(max_concurrent_trials=concurrent or None, reuse_actors=True,
                                            trial_name_creator=lambda t: cell_name(t.config["cell"]),
                                            trial_dirname_creator=lambda t: cell_name(t.config["cell"])),
                run_config=tune.RunConfig(
                    name="grid", storage_path=str(out / "tune"), verbose=0,
                    callbacks=[TrialLines(progress, partial(finished_count, out), cell_name)] if progress else None,
                    # a checkpoint is a pointer to the run folder (_tune_trial): the last one is
                    # all a restore needs (PBT, which clones run folders, keeps copies)
                    checkpoint_config=tune.CheckpointConfig(num_to_keep=1),
                    failure_config=tune.FailureConfig(max_failures=TRIAL_RETRIES)),
            )
        grid = tuner.fit()
    return {**finished, **_collect(grid, cells, out)}


def _collect(grid, cells: Sequence[TrainConfig], out: Path) -> dict[str, Path]:
    """Export the finished trials' last checkpoints; fail naming any that did not finish."""
    steps = {cell_name(c): c.steps for c in cells}
    done, failed, unfinished = {}, [], []
    for result in grid:
        name = cell_name(result.config["cell"])
        if result.error is not None:
            failed.append(f"{name} ({type(result.error).__name__}: {str(result.error).strip().splitlines()[-1][:200]})")
        elif result.checkpoint is None or (result.metrics or {}).get("env_steps", 0) < steps[name]:
            unfinished.append(name)
        else:
            dest = out / "runs" / name
            if not dest.exists():
                run = run_of_checkpoint(result.checkpoint)
                _export(run, dest, move=True)
                shutil.rmtree(out / "trials" / name, ignore_errors=True)
            done[name] = dest
    if failed:
        raise BenchmarkError(f"{len(failed)} trial(s) failed: {'; '.join(failed)}")
    if unfinished:
        raise BenchmarkError(f"interrupted with {len(unfinished)} trial(s) unfinished "
                             f"({', '.join(unfinished[:4])}{', ...' if len(unfinished) > 4 else ''}); "
                             f"continue with the same command and --resume (--out {out})")
    return done


# -- the test protocol and its report ----------------------------------------------------
def report_steps(plan: BenchmarkPlan) -> int:
    """How many times :func:`write_report` calls its ``progress``: once per environment and
    seed tested (the last seed of each environment with its reference policies), once as the
    report starts."""
    return len(plan.envs) * plan.seeds + 1


def write_report(plan: BenchmarkPlan, out: Path, command: Sequence[str] = (),
                 progress: Callable[[str], None] | None = None) -> list[Path]:
    """Scenario 1 and 2 in every environment with that environment's trained policies
    (every seed's, pooled, episodes numbered apart), on held-out episode seeds (from
    eval.testing.validity.HELD_OUT_SEED; training uses small ones), the references of the
    preset, and the `cosim test` report: one test session (eval.testing.session.run_test) per
    environment and seed; ``progress`` is called :func:`report_steps` times, as each session
    ends and as the report starts."""
    import pandas as pd

    from eval.reporting.report import provenance, write_paper_report
    from eval.testing import selection
    from eval.testing.protocol import ProtocolPlan
    from eval.testing.session import TestRequest, run_test
    from eval.testing.validity import HELD_OUT_SEED

    out = Path(out)
    settings = TEST_SETTINGS[plan.preset]
    algos = list(plan.algos)
    frames, tested, first, slots, refs = [], [], {}, [], []
    for env in plan.envs:
        for seed in plan.seed_list:
            ckpts = {}
            for algo in algos:
                run = out / "runs" / cell_name({"env": env, "algo": algo, "seed": seed})
                chosen = selection.choose(run)
                if chosen is None:
                    raise BenchmarkError(f"{run}: no checkpoint; rerun with --resume")
                ckpts[algo] = chosen.path
                first.setdefault(algo, chosen.path)
                tested.append({"env": env, "seed": seed, "algorithm": algo, "path": chosen.path,
                               "selection": chosen})
            last = seed == plan.seed_list[-1]  # the environment's references once, with its last seed
            request = TestRequest(ProtocolPlan(envs=(env,), episodes=settings.episodes, steps=settings.steps,
                                               seed=HELD_OUT_SEED, agents=len(algos)),
                                  tuple(algos), checkpoints={env: ckpts},
                                  references=tuple(settings.references) if last else ())
            slots.append(request.slots.assign(train_seed=seed))
            result = run_test(request)
            # seeds are pooled: number their episodes apart, or the metrics would merge
            # seed 0's episode 0 with seed 1's episode 0
            frames.append(result.records.assign(train_seed=seed, episode=result.records["episode"]
                                                + (seed - plan.first_seed) * settings.episodes))
            if result.references is not None:
                refs.append(result.references)
            if progress:
                progress(f"tested {env} seed {seed}" + (f" and the reference policies ({len(settings.references)})"
                                                        if result.references is not None else ""))
    records = pd.concat(frames, ignore_index=True)
    whole = ProtocolPlan(envs=tuple(plan.envs), episodes=settings.episodes, steps=settings.steps,
                         seed=HELD_OUT_SEED, agents=len(algos))
    if progress:  # one line for the report: the smoke console stays under 40 lines
        progress("the report (tables, figures) ...")
    # every environment's checkpoints, each with its AC and scores (the report's provenance)
    prov = provenance(policy="trained", plan=whole, algos=algos, checkpoints=first,
                      selections={t["algorithm"]: t["selection"] for t in tested if t["env"] == plan.envs[0]
                                  and t["seed"] == plan.first_seed},
                      command=list(command), env_checkpoints=tested, benchmark=plan.to_dict())
    slots = pd.concat(slots, ignore_index=True)  # which checkpoint drove which slot (as `cosim test`)
    prov["slots"] = slots.to_dict("records")
    (out / "report").mkdir(parents=True, exist_ok=True)
    slots.to_csv(out / "report" / "slots.csv", index=False)
    extra = ("\n## Benchmark grid\n\nEvery environment is tested with its own trained policies, "
             f"{plan.seeds} seed(s) pooled (seeds {plan.first_seed}..{plan.seed_list[-1]}, "
             f"`cosim benchmark --preset {plan.preset}`); provenance "
             "lists every checkpoint (environment, seed, algorithm) with its hash and the AC chosen.\n")
    references = pd.concat(refs, ignore_index=True) if refs else None
    if plan.seeds > 1:
        extra += "\n" + seeds_section(plan, out, records, references)
    return write_paper_report(records, out / "report", prov=prov, references=references, extra_md=extra)


def seeds_section(plan: BenchmarkPlan, out: Path, records, references) -> str:
    """With several training seeds, the report's "Over training seeds" section
    (eval/reporting/multiseed.py: each seed's means, the verdict per (algorithm, environment) by
    driving score with intervals over seeds, the IQM of the normalised driving score, the budget
    check of every run), its tables written as CSV files beside the report's."""
    from eval.reporting import multiseed

    runs = {(algo, env, seed): out / "runs" / cell_name({"env": env, "algo": algo, "seed": seed})
            for env in plan.envs for algo in plan.algos for seed in plan.seed_list}
    tables = multiseed.seed_tables(records, references, runs)
    (out / "report").mkdir(parents=True, exist_ok=True)
    for name, table in tables.items():
        table.to_csv(out / "report" / f"{name}.csv", index=False)
    return multiseed.seeds_markdown(tables)
