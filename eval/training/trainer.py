"""The trainer (SPEC §6, "Scenario 1, train"): N ACs of ONE algorithm, each with its
own network, learning together in a driving environment among background cars.

Every algorithm trains on one path (:func:`_train_loop`): ``--envs N`` environments
(one in this process, or N worker processes, ``agents/vector.py``; libsumo allows one
simulation per process) stepped by the one loop, :func:`agents.loop.run_loop`, each AC
acting in all of them in one forward pass, or for A3C one actor-learner thread per
environment (the loop's ``actors``); each AC's finished episodes become CSV rows. The run
folder, resuming and the lock are eval/training/runfolder.py; the CSV, TensorBoard and
checkpoints eval/training/runlog.py.
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from eval.training.config import ASYNC_ALGOS, TrainConfig, TrainError
from eval.training.encoder import run_encoder
from eval.training.plots import plot_convergence
from eval.training.runfolder import (
    RunLock,
    extend_budget,
    load_run_config,
    new_run_dir,
    prune_finished,
    read_state,
    recover_checkpoints,
    resume_keep,
    run_keep,
    write_run_config,
)
from eval.training.runlog import RunLog

log = logging.getLogger(__name__)


def train(cfg: TrainConfig, out: Path = Path("runs"), *, resume: Path | None = None,
          quiet: bool = False, progress: bool = True,
          on_checkpoint: Callable[[Path, int, float], None] | None = None, keep: str = "all",
          steps: int | None = None) -> Path:
    """Run (or resume) one training run; return its folder.

    ``on_checkpoint(run, env_steps, mean_return)`` is called after each committed
    checkpoint (how Ray Tune trials report, eval/scale/benchmark.py and eval/scale/pbt.py).
    ``keep`` is what the folder keeps once the run is finished (eval/training/runfolder.py
    KEEP_POLICIES; ``"all"``, the library default, deletes nothing), recorded in config.yaml; a
    resume keeps all where the run or the resume says ``all`` (runfolder.resume_keep). ``steps`` with ``resume``
    raises the run's budget to that many environment steps (runfolder.extend_budget).

    Raises:
        TrainError: the run folder is held by another process (naming its PID), or
            its config.yaml / state.json is unreadable (naming the file and the key).
    """
    if resume is not None:
        run = Path(resume)
        cfg = load_run_config(run)
        run_encoder(cfg)  # the encoder file the run recorded, by its hash, before anything changes
        lock = RunLock(run)
        try:
            state = read_state(run)
            recover_checkpoints(run, None if state is None else int(state["env_steps"]))
            if steps is not None:
                cfg = extend_budget(run, cfg, 0 if state is None else int(state["env_steps"]), int(steps))
            if run_keep(run) != (keep := resume_keep(run, keep)):  # the run's own --keep, recorded
                write_run_config(run, cfg, keep)
            if state is None:  # stopped before its first checkpoint: start again from step 0
                log.info("resume: %s has no checkpoint yet; restarting it from step 0", run)
                shutil.rmtree(run / "tb", ignore_errors=True)
        except BaseException:
            lock.release()
            raise
    else:
        run_encoder(cfg)  # a missing or unfit --encoder is refused before a run folder exists
        if cfg.init_from is not None:  # a source that does not fit is refused before a run folder exists
            _check_init_source(cfg)
        run = new_run_dir(out, cfg, keep)
        lock = RunLock(run)
        state = None
    try:
        _train_locked(cfg, run, state, quiet, progress, on_checkpoint)
        finished = read_state(run)
        if keep != "all" and finished is not None and int(finished["env_steps"]) >= cfg.steps:
            freed = prune_finished(run, keep)
            log.info("run %s finished: --keep %s freed %.1f MB", run, keep, freed / 1e6)
    finally:
        lock.release()
    return run



def _train_locked(cfg: TrainConfig, run: Path, state: dict | None, quiet: bool, progress: bool,
                  on_checkpoint: Callable[[Path, int, float], None] | None = None) -> None:
    runlog = RunLog(run, cfg, state)
    runlog.on_checkpoint = on_checkpoint
    log.info("training %s on %s with %d ACs for %d steps -> %s", cfg.algo, cfg.env, cfg.agents,
             cfg.steps, run)
    try:
        if runlog.env_steps >= cfg.steps:
            log.info("run %s is already complete (%d steps)", run, runlog.env_steps)
        else:
            _train_loop(cfg, runlog, state is not None, quiet, progress)
    finally:
        runlog.close()
        try:
            plot_convergence(run)
        except OSError as exc:  # a full disk: the error that stopped the run is the one to see
            log.warning("convergence plot of %s not written: %s", run, exc)


def _load_or_build(cfg: TrainConfig, run: Path, resumed: bool, obs_space, act_space,
                   device: str = "cpu") -> dict:
    from agents.base import check_observations
    from agents.registry import get_agent_class

    cls = get_agent_class(cfg.algo)
    if cfg.share_params:  # one network for every AC (agents/shared.py); ac_0's files hold it
        from agents.shared import share

        latest = run / "checkpoints" / "ac_0" / "latest.pt"
        if resumed:
            core = _resume_agent(cfg, run, latest, device)
            try:
                check_observations(core.observation_space, obs_space, f"checkpoint {latest}")
            except ValueError as exc:
                raise TrainError(str(exc)) from None
        else:
            core = cls.from_spaces(obs_space, act_space, cfg.agent_config, seed=cfg.seed, device=device)
            _warm_start(cfg, core, 0)
        return share(core, [f"ac_{k}" for k in range(cfg.agents)])
    out = {}
    for k in range(cfg.agents):
        aid = f"ac_{k}"
        latest = run / "checkpoints" / aid / "latest.pt"
        if resumed:  # saved from any device, loads on any
            out[aid] = _resume_agent(cfg, run, latest, device)
            try:  # a config.yaml edited to another --obs or --frame-stack than the checkpoints'
                check_observations(out[aid].observation_space, obs_space, f"checkpoint {latest}")
            except ValueError as exc:
                raise TrainError(str(exc)) from None
        else:
            # the typed config make_config built (a PPOConfig, ...), as it is
            out[aid] = cls.from_spaces(obs_space, act_space, cfg.agent_config, seed=cfg.seed + k, device=device)
            _warm_start(cfg, out[aid], k)
    return out


def _resume_agent(cfg: TrainConfig, run: Path, latest: Path, device: str):
    """The agent a resumed run goes on training: its ``latest.pt``, which must exist (the run
    has a committed checkpoint), hold ``cfg.algo``, be a full checkpoint and match its checksum.
    Never a fresh agent in its place: the run's step count covers the steps it was trained.

    Raises:
        TrainError: the file is missing, corrupt, of another algorithm or policy-only, in one
            line naming the file and the fix.
    """
    from agents.checkpoint import CheckpointError, load_checkpoint

    fix = ("restore it from a copy, or start the run again from step 0 by deleting its state.json "
           "(the steps trained are lost), or start a new run")
    if not latest.is_file():
        raise TrainError(f"cannot resume {run}: {latest.relative_to(run)} is missing, though state.json "
                         f"counts the steps it trained; {fix}")
    try:
        return load_checkpoint(latest, device=device, expected_algo=cfg.algo, require_full=True)
    except CheckpointError as exc:
        raise TrainError(f"cannot resume: {str(exc).rstrip('.')}. To resume, {fix}") from None


def init_checkpoint(source: str | Path, k: int) -> Path:
    """The checkpoint AC ``k`` of a run warm-started from ``source`` starts from: the file itself,
    or in a run folder checkpoints/ac_k/best.pt (ac_0's where the source has no ac_k)."""
    source = Path(source)
    if source.is_file():
        return source
    own = source / "checkpoints" / f"ac_{k}" / "best.pt"
    return own if own.is_file() else source / "checkpoints" / "ac_0" / "best.pt"


def _check_init_source(cfg: TrainConfig) -> None:
    """Warm-start one agent in memory (the env probed for its spaces), so that ``--init-from``
    with another algorithm or observation fails before anything is written (every AC's source
    comes from the same run, so one is enough)."""
    from agents.registry import get_agent_class

    probe = make_env(cfg)
    try:
        obs_space, act_space = probe.observation_space("ac_0"), probe.action_space("ac_0")
    finally:
        probe.close()
    agent = get_agent_class(cfg.algo).from_spaces(obs_space, act_space, cfg.agent_config, seed=cfg.seed)
    _warm_start(cfg, agent, 0)


def _warm_start(cfg: TrainConfig, agent, k: int) -> None:
    """A fresh agent of a run with ``--init-from``: its policy weights from the source (TrainConfig.init_from)."""
    if cfg.init_from is None:
        return
    from agents.checkpoint import CheckpointError, warm_start

    try:
        warm_start(agent, init_checkpoint(cfg.init_from, k))
    except CheckpointError as exc:
        raise TrainError(f"--init-from: {exc}") from None


def _log_every() -> float:
    """Seconds between the log lines of a --quiet run: 30, or COSIM_LOG_EVERY_S (what
    `cosim train --algo all` sets for the runs whose lines drive its progress bar)."""
    try:
        return float(os.environ.get("COSIM_LOG_EVERY_S", "30"))
    except ValueError:
        return 30.0


def _bar(cfg: TrainConfig, runlog: RunLog, quiet: bool, progress: bool):
    from tqdm import tqdm

    return tqdm(total=cfg.steps, initial=runlog.env_steps, unit="step", dynamic_ncols=True,
                desc=f"{cfg.env} {cfg.algo}", disable=quiet or not progress, smoothing=0.05)


def _report(bar, runlog: RunLog, cfg: TrainConfig, step: int, quiet: bool, last_log: list) -> None:
    mean = runlog.mean_recent()
    bar.set_postfix_str(f"return {mean:8.1f}", refresh=False)
    now = time.monotonic()
    if quiet and now - last_log[0] > _log_every():
        rate = (step - last_log[1]) / (now - last_log[0])
        last_log[0], last_log[1] = now, step
        print(f"[{cfg.algo} {cfg.env}] step {step}/{cfg.steps} recent mean return {mean:.1f} "
              f"({rate:.0f} steps/s)", flush=True)


def _train_loop(cfg: TrainConfig, runlog: RunLog, resumed: bool, quiet: bool, progress: bool) -> None:
    """Every algorithm: ``cfg.envs`` environments (worker processes when > 1) stepped by the
    one loop, agents.loop.run_loop (docs/agents.md): one batched forward pass per AC per step,
    or for A3C one actor-learner thread per environment (agents.registry ``actors``). One
    progress record, one checkpoint rule (each multiple of ``checkpoint_every`` crossed, and
    the end), one reseed rule (episodes after a resume: ``seed + 100003 * episodes so far``)."""
    from agents import registry
    from agents.base import resolve_device
    from agents.loop import run_loop
    from agents.vector import make_vector_env

    _set_torch_threads(cfg)
    try:  # A3C's and IMPALA's learners stay on the CPU, as their trainers always built them
        device = "cpu" if cfg.algo in ASYNC_ALGOS else resolve_device(cfg.device)
    except ValueError as exc:
        raise TrainError(str(exc)) from None
    start_step = runlog.env_steps
    # --demo-steps: the agents are built and fed in the demonstration env, closed before the
    # vector env opens its own (libsumo runs one simulation per process)
    agent_map = _demonstrate(cfg, runlog.run, resumed, device, quiet, progress) if cfg.demo_steps else None
    # env i of N: seed + i (env 0 is the one-env run's env)
    env = make_vector_env([functools.partial(make_env, cfg, cfg.seed + i) for i in range(cfg.envs)])
    repeat = cfg.agent_config.action_repeat  # the loop counts decisions, the budget env steps
    last = [start_step]
    bar = _bar(cfg, runlog, quiet, progress)
    last_log = [time.monotonic(), start_step]
    try:
        if agent_map is None:
            agent_map = _load_or_build(cfg, runlog.run, resumed, env.observation_space("ac_0"),
                                       env.action_space("ac_0"), device)

        def callback(p) -> bool:
            now = start_step + p.env_steps * repeat
            before, last[0] = last[0], now
            for aid, summary in p.summaries:
                runlog.episode(aid, summary, now)
            for aid, m in p.metrics.items():
                runlog.metrics(aid, {k: v for k, v in m.items() if np.isscalar(v)}, now)
            bar.update(now - before)
            if now // cfg.checkpoint_every > before // cfg.checkpoint_every or now >= cfg.steps:
                runlog.checkpoint(agent_map, now, p.timing)
            _report(bar, runlog, cfg, now, quiet, last_log)
            return now >= cfg.steps

        # episodes after a resume get fresh seeds: seed + 100003 * (episodes so far)
        first_seed = cfg.seed + 100_003 * sum(runlog.episodes.values())
        actors = registry.get_actors(cfg.algo)
        run_loop(agent_map, env, total_steps=decisions(cfg, start_step), callback=callback, seed=first_seed,
                 learner_threads=_learner_threads(cfg),
                 actors=None if actors is None else actors(agent_map, first_seed))
    finally:
        bar.close()
        env.close()


def _demonstrate(cfg: TrainConfig, run: Path, resumed: bool, device: str, quiet: bool = True,
                 progress: bool = False) -> dict:
    """``--demo-steps``: the run's agents, built (or resumed) in the demonstration env with the
    autopilot's transitions in every AC's replay (as environment 0's), then on a fresh run
    ``--demo-updates`` pre-training steps, each under a progress bar (a line when each ends
    with ``quiet``); logged to run/demos.json (eval/training/demos.py)."""
    from eval.training import demos

    def build(obs_space, act_space) -> dict:
        agent_map = _load_or_build(cfg, run, resumed, obs_space, act_space, device)
        for agent in agent_map.values():  # the replay's rings, before anything is stored
            agent.prepare_envs(cfg.envs)
        return agent_map

    def say(text: str) -> None:  # --quiet: a line on stdout (what `--algo all` relays); else the log
        if quiet:
            print(text, flush=True)
        else:
            log.info(text)

    bars = progress and not quiet
    agent_map, summary = demos.demonstrate(cfg, build, make_env, progress=bars)
    say(f"[{cfg.algo} {cfg.env}] demonstrations: {summary['env_steps']} env steps in {summary['episodes']} "
        f"autopilot episodes ({summary['seconds']:.0f} s)")
    if not resumed and cfg.demo_updates:
        start = time.monotonic()
        metrics = demos.pretrain(agent_map, cfg.demo_updates, progress=bars)
        summary["pretrain"] = {"updates": cfg.demo_updates, "metrics": metrics,
                               "seconds": round(time.monotonic() - start, 1)}
        say(f"[{cfg.algo} {cfg.env}] pre-training: {cfg.demo_updates} updates per network "
            f"({summary['pretrain']['seconds']:.0f} s)")
    demos.record(run, summary)
    return agent_map


def _cpus() -> int:
    """CPUs this run may use: OMP_NUM_THREADS when set (Ray sets it per trial), else all."""
    return int(os.environ.get("OMP_NUM_THREADS") or 0) or os.cpu_count() or 1


def _learner_threads(cfg: TrainConfig) -> int:
    """``cfg.learner_threads``, or one per AC up to the CPUs (the ACs' updates are independent);
    1 when the ACs share one network (--share-params: one learner)."""
    if cfg.share_params:
        return 1
    return cfg.learner_threads or min(cfg.agents, _cpus())


def _set_torch_threads(cfg: TrainConfig) -> None:
    """``cfg.torch_threads``, or the CPUs the env workers leave (all when the env runs in this
    process) shared among the learner threads, at least 1; A3C's learner threads are its
    parallelism (1 torch thread). IMPALA's one learner gets the same share as the
    parallel ACs would (1 on 2 cores): more OpenMP threads were not measured to help. Two OpenMP threads per update on a busy 2-core machine
    made a forward pass ~20x slower (docs/benchmarks.md#where-ppos-cpu-goes-with-1-and-2-envs): parallel ACs, not
    parallel ops, use the cores here."""
    import torch

    from agents import registry

    spare = max(1, _cpus() - cfg.envs) if cfg.envs > 1 else _cpus()
    # a run with --share-params has one learner thread but keeps the torch threads of the
    # independent layout: on 2 busy cores its PPO ran at 2 env steps/s with 2 OpenMP threads,
    # against 20 for the same run without sharing with 1
    learners = min(cfg.agents, _cpus()) if cfg.share_params and not cfg.learner_threads else _learner_threads(cfg)
    threads = cfg.torch_threads or (1 if registry.get(cfg.algo).thread_per_env
                                    else max(1, spare // learners))
    torch.set_num_threads(threads)


def make_env(cfg: TrainConfig | dict, worker_seed: int | None = None):
    """Build the training env of a config, a TrainConfig or its ``to_dict()`` (top-level, so
    worker processes can pickle it; a TrainConfig pickles without torch);
    with ``frame_stack`` K > 1 each AC observes its last K frames (cosim.wrappers.FrameStack),
    with ``obs`` "nav" beside its measurements (cosim.wrappers.NavObservation), with the
    agents' ``action_repeat`` R > 1 each action held for R steps (cosim.wrappers.ActionRepeat);
    collisions end an AC's episode unless ``collisions_end_episode`` is off; with
    ``stall_truncate`` N an episode is truncated once every AC has stood still N steps; with
    ``encoder`` each AC observes the frozen encoder's features of its last K frames
    (eval.training.encoder.observation)."""
    from cosim.env import CosimParallelEnv
    from eval.training.encoder import observation

    cfg = cfg if isinstance(cfg, TrainConfig) else TrainConfig(**cfg)
    env = CosimParallelEnv(
        cfg.env, num_agents=cfg.agents, action_types=cfg.action_type,
        seed=cfg.seed if worker_seed is None else worker_seed, image_size=cfg.image_size,
        horizon=cfg.horizon, terminate_on_collision=cfg.collisions_end_episode,
        collision_charge=cfg.collision_charge, collision_fault=cfg.collision_fault,
        stall_truncate=cfg.stall_truncate or None,
    )
    # with --envs N > 1 this is a worker process of one env: its encoder forward on one thread
    return observation(env, cfg, threads=1 if cfg.envs > 1 else None)


def decisions(cfg: TrainConfig, start_step: int) -> int:
    """Steps of the training env (decisions) left in the budget: ``cfg.steps`` counts
    environment steps, and with the agents' ``action_repeat`` R each decision is R of them
    (docs/task.md, "Action repeat")."""
    return -(-(cfg.steps - start_step) // cfg.agent_config.action_repeat)
