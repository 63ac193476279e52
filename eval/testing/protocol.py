"""The test protocol (SPEC §6): it runs the episodes and records every step; the report
(SPEC §7) is written from those records by :mod:`eval.reporting.report`.

Scenario 1 (multi-agent): the trained ACs, one per algorithm, drive together in
each environment among background cars (and pedestrians in env_2/env_3);
discrete and continuous agents share one environment.
Scenario 2 (single-agent): each AC alone, no other vehicles, no pedestrians.

In Scenario 1 the algorithms take turns at the spawn points: in episode ``e`` the
algorithm at position ``i`` of the order drives slot ``ac_{(i + e) mod N}``
(:func:`slot_order`), so no algorithm is tied to one spawn (in env_1 with 6 ACs ``ac_0``
starts 25 m behind ``ac_4`` and ``ac_2`` 25 m behind ``ac_5`` in the same lane; the other
slots have a free lane ahead).
With a multiple of N episodes every algorithm starts from every spawn equally often.
``ProtocolPlan(rotate=False)`` keeps algorithm ``i`` in ``ac_i``.

Collisions do not end an episode in testing (the metrics count steps in
collision). Every step of every AC is recorded (:mod:`eval.testing.records`); metrics,
tables and plots are computed from those records.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from agents import registry
from agents.observations import image_space
from cosim.errors import CosimError
from eval.labels import ENVS
from eval.testing import selection
from eval.testing.conditions import TestConditions, action_kinds
from eval.testing.metrics import METRICS, episode_metrics, scenario_dt, success_rates, summarize
from eval.testing.rollout import (
    AutopilotPolicy,
    NavPolicy,
    RandomPolicy,
    RepeatPolicy,
    SampledPolicy,
    StackedPolicy,
    StatePolicy,
    run_episodes,
    use_cameras,
)

log = logging.getLogger(__name__)

ALGO_ORDER = tuple(registry.ALGORITHMS)  # the catalogue's order (agents/registry.py)
CONTINUOUS = registry.CONTINUOUS
SAMPLED = registry.STOCHASTIC
"""Algorithms whose learned policy is a distribution (the catalogue's ``stochastic``: PPO,
A3C, IMPALA): the test samples it (their training maximised the return of the sampled
policy; its mode is a different policy: two IMPALA modes crawled at 8-14 km/h and reached no goal where their samples drove;
task version 1; in git history at 1b59d82, docs/results/2026-11-23-greedy-vs-sampled). DQN, DDPG and TD3 learn a
deterministic policy and act greedily (no epsilon, no action noise). ``cosim test
--greedy`` takes every policy's mode."""


class ProtocolError(CosimError, ValueError):
    """The test cannot run as asked; the message says what to change."""


@dataclass(frozen=True)
class ProtocolPlan:
    envs: tuple[str, ...] = ENVS
    scenarios: tuple[int, ...] = (1, 2)
    episodes: int = 3
    steps: int = 500
    seed: int = 0
    agents: int = 6
    rotate: bool = True
    greedy: bool = False  # True: every policy's mode, also for SAMPLED algorithms


def rules(plan: ProtocolPlan) -> dict[str, str]:
    """How the plan places ACs and picks actions, in words (report provenance, science plan)."""
    return {
        "scenario_1_slots": ("rotated: algorithm i drives ac_{(i + episode) mod N}" if plan.rotate
                             else "fixed: algorithm i drives ac_i"),
        "slot_checkpoints": "a run's AC trained in a slot drives that slot; other slots the "
                            "checkpoint listed (eval.testing.protocol.slot_checkpoint)",
        "actions": ("every policy's mode (--greedy)" if plan.greedy else
                    f"{', '.join(SAMPLED)} sample their policy; {', '.join(registry.DETERMINISTIC)} "
                    "greedy (eval.testing.protocol.SAMPLED)"),
    }


def slot_order(algos: Sequence[str], episode: int, rotate: bool = True) -> list[str]:
    """The algorithm of each Scenario 1 slot (``ac_0``, ``ac_1``, ...) in ``episode``:
    algorithm ``i`` drives slot ``(i + episode) mod N`` (module docstring)."""
    algos = list(algos)
    r = episode % len(algos) if rotate and algos else 0
    return algos[len(algos) - r:] + algos[: len(algos) - r]


def run_env(run: Path) -> str | None:
    """The environment a run folder trained in: its config.yaml's ``env`` (a name, or a
    scenario file's stem), else the first field of its name (``<env>__<algo>__<seed>__<stamp>``);
    None when neither says."""
    import yaml

    run = Path(run)
    try:
        env = (yaml.safe_load((run / "config.yaml").read_text()) or {}).get("env")
    except (OSError, ValueError, AttributeError, yaml.YAMLError):
        env = None
    if env:
        return Path(str(env)).stem
    parts = run.name.split("__")
    return parts[0] if len(parts) >= 4 and parts[0] else None


def run_of(checkpoint: Path) -> Path | None:
    """The run folder a checkpoint is in (``<run>/checkpoints/ac_k/best.pt``); None for a
    file outside a run folder."""
    checkpoint = Path(checkpoint)
    return checkpoint.parent.parent.parent if checkpoint.parent.parent.name == "checkpoints" else None


def trained_env(checkpoint: Path) -> str | None:
    """The environment a checkpoint's run trained in (:func:`run_env`); None for a file
    outside a run folder."""
    run = run_of(checkpoint)
    return run_env(run) if run is not None else None


def find_checkpoints(runs: Path, algos: Sequence[str], env: str | None = None) -> dict[str, Path]:
    """The newest run of each algorithm under `runs` (with ``env``: the newest trained in that
    environment, else the newest of any, which :func:`cross_env` then names); the checkpoint of
    the AC that represents it (eval/testing/selection.py: best training score, best.pt else latest.pt)."""
    found: dict[str, Path] = {}
    runs = Path(runs)
    folders = sorted(runs.glob("*__*__*__*"), key=lambda p: p.stat().st_mtime, reverse=True) if runs.exists() else []
    if env is not None:  # stable: the environment's own runs first, each group newest first
        folders.sort(key=lambda run: run_env(run) != Path(env).stem)
    for algo in algos:
        for run in folders:
            if run.name.split("__")[1] != algo:
                continue
            chosen = selection.choose(run)  # which AC represents the run: eval/testing/selection.py
            if chosen is not None:
                found[algo] = chosen.path
                break
    missing = [a for a in algos if a not in found]
    if missing:
        raise ProtocolError(
            f"no trained checkpoint under {runs} for {', '.join(missing)}; train them with "
            f"`cosim train --algo {missing[0]}` (or --algo all), or test a reference with "
            "--policy autopilot / --policy random"
        )
    return found


PolicyFactory = Callable[[object, str, str], object]  # (env, agent id, algorithm) -> policy


def load_for_slot(path: Path, algo: str, image_size: int = 84):
    """Load the checkpoint given for `algo`'s AC, refusing one that cannot drive it
    (a checkpoint trained on K stacked frames is tested on K, one trained on the nav
    observation with its measurements: :func:`drive`).

    Raises:
        agents.CheckpointError: the file is missing or corrupt.
        ProtocolError: it holds another algorithm, an action space of the other kind
            (a continuous actor in a discrete slot) or another camera size; the
            message names the file.
    """
    import gymnasium

    import agents

    agent = agents.load(path)
    if agent.algo != algo:
        raise ProtocolError(
            f"checkpoint {path} holds a {agent.algo} agent, but it was given for the {algo} AC; "
            f"give it as {agent.algo}, or a {algo} checkpoint for {algo}"
        )
    discrete = isinstance(agent.action_space, gymnasium.spaces.Discrete)
    if discrete != (algo not in CONTINUOUS):
        want = "continuous Box(-1, 1, (2,))" if algo in CONTINUOUS else "discrete Discrete(9)"
        raise ProtocolError(
            f"checkpoint {path} acts in {agent.action_space}, but the {algo} AC needs a {want} "
            "action space; give a checkpoint trained with that action type"
        )
    shape = tuple(image_space(agent.observation_space).shape)
    if obs_of(agent) != "state" and (len(shape) != 3 or shape[:2] != (image_size, image_size)
                                     or shape[2] % 3 or not shape[2]):
        raise ProtocolError(
            f"checkpoint {path} sees observations of shape {shape}, the test environments give "
            f"{(image_size, image_size, 3)} camera images (or K of them stacked, "
            f"{(image_size, image_size, '3K')}); give a checkpoint trained on them"
        )
    return agent


def frame_stack_of(agent) -> int:
    """Camera frames a checkpoint's agent observes at once: its image channels / 3
    (a run trained with ``frame_stack`` K has 84x84x3K images); 1 for the state track."""
    return 1 if obs_of(agent) == "state" else int(image_space(agent.observation_space).shape[-1]) // 3


def obs_of(agent) -> str:
    """The observation variant a checkpoint's agent was trained on (``cosim train --obs``):
    "nav" for a ``Dict(image, measurements)`` observation space, "state" for a vector
    (agents.base.observation_variant), else "image"."""
    from agents.base import observation_variant

    return observation_variant(agent.observation_space)


def drive(agent, sample_seed: int | None = None, env=None, slot: str | None = None):
    """The policy of one AC from a loaded checkpoint: the agent itself (or, with
    ``sample_seed``, a :class:`~eval.testing.rollout.SampledPolicy` drawing its actions) for
    one frame; for a nav-trained agent inside a :class:`~eval.testing.rollout.NavPolicy` that
    builds the measurements of AC ``slot`` of ``env``; inside a
    :class:`~eval.testing.rollout.StackedPolicy` with that AC's own frame history when it was
    trained on K frames; inside a :class:`~eval.testing.rollout.RepeatPolicy` that holds each
    action for the checkpoint's ``action_repeat`` steps when it was trained with one. All read
    from the checkpoint, so ACs of every variant share one test environment.

    Raises:
        ProtocolError: a nav-trained agent without the env and slot it drives.
    """
    k = frame_stack_of(agent)
    policy = agent if sample_seed is None else SampledPolicy(agent, sample_seed)
    if obs_of(agent) == "nav":
        if env is None or slot is None:
            raise ProtocolError(f"{agent.algo} was trained with --obs nav: give drive() the test env and "
                                "the AC slot it drives, to build that AC's measurements")
        policy = NavPolicy(policy, env, slot)
    if obs_of(agent) == "state":  # its own state vector, from the shared test env's world
        if env is None or slot is None:
            raise ProtocolError(f"{agent.algo} was trained with --obs state: give drive() the test env and "
                                "the AC slot it drives, to build that AC's state vector")
        policy = StatePolicy(policy, env, slot)
    policy = StackedPolicy(policy, k) if k > 1 else policy
    return RepeatPolicy(policy, repeat) if (repeat := action_repeat_of(agent)) > 1 else policy


def action_repeat_of(agent) -> int:
    """Environment steps a checkpoint's agent holds each action for (its config's
    ``action_repeat``; 1 for a checkpoint written before the option)."""
    return int(getattr(getattr(agent, "config", None), "action_repeat", 1))


def slot_checkpoint(path: Path, slot: str) -> Path:
    """The checkpoint that drives ``slot`` for an algorithm represented by ``path``: the
    AC of the same run trained in that slot when there is one (its route: the camera
    carries no route command, so an image-trained AC knows only the turns it was trained on), else
    ``path`` itself (eval/testing/selection.py's choice)."""
    path = Path(path)
    if path.parent.parent.name != "checkpoints":
        return path
    own = selection.checkpoint_of(path.parent.parent.parent, slot)
    return own if own is not None else path


def cross_env(per_env: Mapping[str, Mapping[str, Path]]) -> list[tuple[str, Path, str, str]]:
    """``(algorithm, checkpoint, trained in, tested in)`` of every checkpoint that drives an
    environment other than the one its run trained in (``per_env``: environment -> algorithm ->
    checkpoint); a checkpoint outside a run folder has no known environment and is not listed."""
    found = []
    for env, ckpts in per_env.items():
        for algo, path in ckpts.items():
            trained = trained_env(path)
            if trained is not None and trained != Path(env).stem:
                found.append((algo, Path(path), trained, env))
    return found


def slot_table(per_env: Mapping[str, Mapping[str, Path]], plan: ProtocolPlan, algos: Sequence[str],
               fixed: Collection[str] = ()) -> pd.DataFrame:
    """Which checkpoint drives which slot in which environment (what :func:`policy_factory`
    loads): one row per environment, algorithm and slot: ``env, algorithm, slot, scenarios``
    (the test scenarios that drive the slot: Scenario 1 rotates the algorithms over every slot,
    Scenario 2 drives ac_0 alone), ``checkpoint, ac`` (the AC folder it comes from), ``how``
    (``own slot``: the run's AC trained in that slot; ``chosen AC``: the run's representative,
    eval/testing/selection.py; ``given``: ``--checkpoint``), ``run, trained_env, cross_env``."""
    algos = list(algos)[: plan.agents] if 1 in plan.scenarios else list(algos)
    slots = [f"ac_{k}" for k in range(len(algos))] if 1 in plan.scenarios else ["ac_0"]
    rows = []
    for env, ckpts in per_env.items():
        for algo in algos:
            chosen = Path(ckpts[algo])
            for slot in slots:
                path = chosen if algo in fixed else slot_checkpoint(chosen, slot)
                how = "given" if algo in fixed else "own slot" if path.parent.name == slot else "chosen AC"
                scen = [n for n in plan.scenarios if n == 1 or slot == "ac_0"]
                trained = trained_env(path)
                rows.append({"env": env, "algorithm": algo, "slot": slot,
                             "scenarios": " ".join(map(str, scen)), "checkpoint": str(path),
                             "ac": path.parent.name if path.parent.name.startswith("ac_") else "-",
                             "how": how,
                             "run": str(run_of(path) or ""),
                             "trained_env": trained or "unknown",
                             "cross_env": trained is not None and trained != Path(env).stem})
    return pd.DataFrame(rows)


def _summary_rows(table: pd.DataFrame) -> list[list[str]]:
    """The head and rows of :func:`slot_summary`: a row per algorithm and run (or file), the
    environments it drives in one cell, the AC folder driving each slot."""
    slots = list(dict.fromkeys(table["slot"]))
    grouped: dict[tuple, list[str]] = {}
    for (env, algo), g in table.groupby(["env", "algorithm"], sort=False):
        g = g.set_index("slot")
        cells = tuple("given" if g.at[s, "how"] == "given" else
                      g.at[s, "ac"] + ("*" if g.at[s, "how"] == "chosen AC" else "") for s in slots)
        first = g.iloc[0]
        key = (algo, first["run"] or first["checkpoint"], first["trained_env"], bool(g["cross_env"].any()), cells)
        grouped.setdefault(key, []).append(env)
    rows = [["tested in", "algorithm", "trained in", *slots, "run (or file)"]]
    for (algo, source, trained, cross, cells), envs in grouped.items():
        rows.append([" ".join(envs), algo, trained + (" (!)" if cross else ""), *cells, source])
    return rows


def slot_summary(table: pd.DataFrame) -> str:
    """:func:`slot_table` as one compact text table (the console's): a row per algorithm and
    run, the environments it drives in one cell, then the AC folder driving each slot (``*``:
    the run's chosen AC, where it trained no AC in that slot; ``given``: a ``--checkpoint``
    file; ``(!)``: trained in another environment than it drives)."""
    if table.empty:
        return ""
    rows = _summary_rows(table)
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r[:-1], widths, strict=True)) + "  " + r[-1] for r in rows)


SLOTS_NOTE = ("Scenario 1 rotates the algorithms over every slot, Scenario 2 drives `ac_0` alone. "
              "A slot is driven by the run's AC trained in that slot; `*`: the run trained no AC "
              "there and its chosen AC drives it; `given`: a `--checkpoint` file drives every slot; "
              "\"(!)\": trained in another environment than the one tested (`--allow-cross-env`).")


def slots_markdown(table: pd.DataFrame) -> str:
    """:func:`slot_table` for the report page: a section with the compact table (as Markdown)."""
    if table.empty:
        return ""
    rows = _summary_rows(table)
    lines = ["\n## Checkpoints per environment and slot\n",
             f"Which checkpoint drives which AC slot in each tested environment (`slots.csv`). {SLOTS_NOTE}\n",
             "| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
    lines += ["| " + " | ".join(r[:-1]) + f" | `{r[-1]}` |" for r in rows[1:]]
    return "\n".join(lines) + "\n"


def slot_index(agent: str) -> int:
    """k of slot ``ac_k``: the seed of that slot's draws."""
    return int(agent.rsplit("_", 1)[1])


class TrainedPolicies:
    """:func:`policy_factory` ("trained"), as an object a test worker process can receive:
    pickled without the loaded networks, it loads each checkpoint again where it runs."""

    def __init__(self, checkpoints: dict[str, Path] | None = None, fixed: Collection[str] = (),
                 greedy: bool = False, loaded: dict | None = None):
        self.checkpoints = dict(checkpoints or {})
        self.fixed, self.greedy = tuple(fixed), greedy
        self.loaded = {} if loaded is None else loaded
        for a, p in self.checkpoints.items():  # the given ones load now: a bad file fails before any episode runs
            if p not in self.loaded:
                self.loaded[p] = load_for_slot(p, a)

    def __call__(self, env, agent: str, algo: str):
        path = (self.checkpoints[algo] if algo in self.fixed
                else slot_checkpoint(self.checkpoints[algo], agent))
        if path not in self.loaded:
            self.loaded[path] = load_for_slot(path, algo)
        seed = slot_index(agent) if algo in SAMPLED and not self.greedy else None
        return drive(self.loaded[path], seed, env, agent)  # one frame history (and draw stream) per AC

    def __getstate__(self) -> dict:
        return {**self.__dict__, "loaded": {}}


class EnvPolicies:
    """:func:`env_policy_factory`'s factory: each environment's own :class:`TrainedPolicies`."""

    def __init__(self, by_name: dict[str, TrainedPolicies]):
        self.by_name = by_name

    def __call__(self, env, agent: str, algo: str):
        return self.by_name[env.scenario.name](env, agent, algo)


class ReferencePolicies:
    """``--policy autopilot`` or ``random`` for every AC (random seeded by the AC's slot)."""

    def __init__(self, kind: str):
        self.kind = kind

    def __call__(self, env, agent: str, algo: str):
        if self.kind == "autopilot":
            return AutopilotPolicy(env, agent)
        return RandomPolicy(env.action_space(agent), seed=slot_index(agent))


def env_policy_factory(per_env: Mapping[str, Mapping[str, Path]], fixed: Collection[str] = (),
                       greedy: bool = False) -> PolicyFactory:
    """:func:`policy_factory` ("trained") with each environment's own checkpoints
    (``per_env``: environment name or scenario file -> algorithm -> checkpoint); a checkpoint
    several environments share is loaded once."""
    from cosim.scenario import load_scenario

    loaded: dict[Path, object] = {}
    return EnvPolicies({load_scenario(env).name: TrainedPolicies(dict(ckpts), fixed, greedy, loaded)
                        for env, ckpts in per_env.items()})


def policy_factory(kind: str, checkpoints: dict[str, Path] | None = None,
                   fixed: Collection[str] = (), greedy: bool = False,
                   loaded: dict | None = None) -> PolicyFactory:
    """How each AC gets its policy: trained checkpoints, the autopilot, or random.

    Trained: slot ``ac_k`` of algorithm ``a`` is driven by :func:`slot_checkpoint`
    (the run's own ``ac_k`` where it trained one), except for the algorithms in
    ``fixed`` (given with ``--checkpoint``), whose checkpoint drives every slot. The
    :data:`SAMPLED` algorithms draw their actions from their policy (seeded per slot
    and episode) unless ``greedy``; the others act greedily. ``loaded``: a cache of loaded
    checkpoints (path -> agent) to share with other factories. Every factory returned can be
    pickled, so :func:`run_protocol` can hand it to worker processes."""
    if kind == "trained":
        return TrainedPolicies(checkpoints, fixed, greedy, loaded)
    if kind in ("autopilot", "random"):
        return ReferencePolicies(kind)
    raise ProtocolError(f"unknown policy kind {kind!r}; valid: trained, autopilot, random")


@dataclass(frozen=True)
class ProtocolJob:
    """One environment of the test: a Scenario 1 slot order with the episodes that use it,
    or one algorithm's AC alone (Scenario 2) for every episode."""

    env: str
    scenario: int
    order: tuple[str, ...]  # the algorithm of ac_0, ac_1, ...
    episodes: tuple[int, ...]


def protocol_jobs(plan: ProtocolPlan, algos: Sequence[str]) -> list[ProtocolJob]:
    """The plan's environments to run, in the order their records are returned."""
    jobs = []
    for env_name in plan.envs:
        if 1 in plan.scenarios:
            # one environment per slot order (the action types follow the algorithms)
            by_order: dict[tuple[str, ...], list[int]] = {}
            for e in range(plan.episodes):
                by_order.setdefault(tuple(slot_order(algos, e, plan.rotate)), []).append(e)
            jobs += [ProtocolJob(env_name, 1, order, tuple(eps)) for order, eps in by_order.items()]
        if 2 in plan.scenarios:
            jobs += [ProtocolJob(env_name, 2, (algo,), tuple(range(plan.episodes))) for algo in algos]
    return jobs


def run_job(plan: ProtocolPlan, make_policy: PolicyFactory, job: ProtocolJob) -> pd.DataFrame:
    """Every step of one :class:`ProtocolJob`'s episodes (episode seeds ``plan.seed + e``)."""
    env = TestConditions.of(job.scenario, plan.steps).env(job.env, action_kinds(list(job.order)))
    try:
        agent_algo = dict(zip(env.possible_agents, job.order, strict=True))
        policies = {a: make_policy(env, a, agent_algo[a]) for a in env.possible_agents}
        use_cameras(env, policies)  # off when no AC reads an image (state-track / reference ACs only)
        rec = run_episodes(env, policies, [plan.seed + e for e in job.episodes], algorithms=agent_algo)
    finally:
        env.close()
    rec["episode"] = rec["episode"].map(dict(enumerate(job.episodes)))
    return rec.assign(env=job.env, scenario=job.scenario)


_WORKER_POLICIES: list = []  # a test worker process's policy factory (set by _start_worker)


def _start_worker(make_policy: PolicyFactory, owner: int | None = None) -> None:
    import torch

    if owner is not None:  # the test's process dies (kill -9, SIGTERM): its workers go too
        from agents.workers import die_with_owner

        die_with_owner(owner)
    torch.set_num_threads(1)  # the workers share the machine's cores
    _WORKER_POLICIES[:] = [make_policy]


def _worker_job(plan: ProtocolPlan, job: ProtocolJob) -> pd.DataFrame:
    return run_job(plan, _WORKER_POLICIES[0], job)


def _job_file(save: Path, k: int) -> Path:
    return save / f"job-{k:03d}.parquet"


def _kept_jobs(save: Path, plan: ProtocolPlan, jobs: list[ProtocolJob]) -> dict[int, pd.DataFrame]:
    """``save``'s records of the jobs an earlier, interrupted run of the same plan finished
    (job index -> records); ``save`` is created and its plan.json written on a first run.

    Raises:
        ProtocolError: ``save`` holds the episodes of another plan, or cannot be written.
    """
    import dataclasses
    import json

    from eval.testing.files import atomic_write, write_message

    def error(p: Path, exc: OSError) -> ProtocolError:
        return ProtocolError(write_message(p, exc, "the episodes already kept are not run again"))

    want = json.loads(json.dumps({"plan": dataclasses.asdict(plan), "jobs": [dataclasses.asdict(j) for j in jobs]}))
    path = save / "plan.json"
    try:
        save.mkdir(parents=True, exist_ok=True)
        if not path.exists():
            atomic_write(path, json.dumps(want, indent=1), error)
            return {}
        saved = json.loads(path.read_text())
    except ProtocolError:
        raise
    except (OSError, ValueError) as exc:
        raise ProtocolError(f"{path}: {exc}; delete {save} to run the test afresh") from None
    if saved != want:
        raise ProtocolError(f"{save} holds the episodes of another test plan ({path}); give the options "
                            "of the test that started it, or another --out")
    kept = {}
    for k in range(len(jobs)):
        if _job_file(save, k).is_file():
            try:
                kept[k] = pd.read_parquet(_job_file(save, k))
            except Exception as exc:  # a file cut by a kill is renamed into place whole, so a bug or a disk fault
                raise ProtocolError(f"{_job_file(save, k)} is unreadable ({type(exc).__name__}); delete it "
                                    "to run its episodes again") from None
    return kept


def _keep_job(save: Path | None, k: int, records: pd.DataFrame) -> None:
    """Write job ``k``'s records under ``save`` (a temporary name, renamed: whole or absent)."""
    if save is None:
        return
    path = _job_file(save, k)
    tmp = path.with_name(path.name + ".tmp")
    try:
        records.to_parquet(tmp, index=False)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        from eval.testing.files import write_message

        raise ProtocolError(write_message(path, exc, "the episodes already kept are not run again")) from exc


def run_protocol(plan: ProtocolPlan, make_policy: PolicyFactory, algos: Sequence[str] = ALGO_ORDER,
                 progress: Callable[[str], None] | None = None, workers: int = 1,
                 save: Path | None = None) -> pd.DataFrame:
    """Run Scenario 1 and/or 2 in every environment of the plan; return all records.

    ``workers`` > 1 runs the plan's :func:`protocol_jobs` in that many processes (each with one
    torch thread, each ending with this process, even on kill -9); the records are the same, in
    the same order, as with one. ``progress`` is told "<env> scenario 1" when an environment's
    Scenario 1 is done and "<env> scenario 2 <algo>" for each AC alone.

    ``save``: a folder where each job's records are written as it ends (``job-<k>.parquet``,
    beside the plan in plan.json); a run interrupted (Ctrl-C, kill -9, a full disk) and started
    again with the same plan and folder runs only the jobs not kept there, and returns the same
    records as one run without interruption.

    Raises:
        ProtocolError: ``save`` holds another plan's episodes, or cannot be written.
    """
    algos = list(algos)[: plan.agents] if 1 in plan.scenarios else list(algos)
    jobs = protocol_jobs(plan, algos)
    left = {env: sum(j.env == env and j.scenario == 1 for j in jobs) for env in plan.envs}

    def done(job: ProtocolJob) -> None:
        if job.scenario == 1:
            left[job.env] -= 1
        if progress and (job.scenario == 2 or not left[job.env]):
            progress(f"{job.env} scenario {job.scenario}" + (f" {job.order[0]}" if job.scenario == 2 else ""))

    save = None if save is None else Path(save)
    results: list[pd.DataFrame | None] = [None] * len(jobs)
    for k, records in (_kept_jobs(save, plan, jobs) if save is not None else {}).items():
        results[k] = records
        done(jobs[k])
    todo = [k for k in range(len(jobs)) if results[k] is None]
    workers = max(1, min(int(workers), len(todo)))
    if workers == 1:
        for k in todo:
            results[k] = run_job(plan, make_policy, jobs[k])
            _keep_job(save, k, results[k])
            done(jobs[k])
        return pd.concat(results, ignore_index=True) if results else pd.DataFrame()
    import multiprocessing
    import pickle
    from concurrent.futures import ProcessPoolExecutor, as_completed

    try:
        pickle.dumps(make_policy)
    except (pickle.PicklingError, AttributeError, TypeError) as exc:
        raise ProtocolError(f"workers={workers}: this policy factory cannot go to another process "
                            f"({exc}); use policy_factory(...) or workers=1") from exc
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_start_worker, initargs=(make_policy, os.getpid()))
    try:
        running = {pool.submit(_worker_job, plan, jobs[k]): k for k in todo}
        for future in as_completed(running):
            k = running[future]
            results[k] = future.result()
            _keep_job(save, k, results[k])
            done(jobs[k])
    except BaseException:  # Ctrl-C, SIGTERM, a failed job: the workers stop now, not after their jobs
        _stop_pool(pool)
        raise
    pool.shutdown()
    return pd.concat(results, ignore_index=True)


def _stop_pool(pool) -> None:
    """End a ProcessPoolExecutor's workers at once (their jobs cancelled) and wait for them."""
    processes = list(getattr(pool, "_processes", {}).values())  # the executor keeps no other handle
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes:
        proc.kill()
    for proc in processes:
        proc.join(timeout=10)


def metrics_table(records: pd.DataFrame, dt: float | None = None) -> pd.DataFrame:
    """Per (scenario, env, algorithm): mean over episodes of every SPEC §4 metric (``dt``:
    seconds per step; None: each environment's scenario's, eval.testing.metrics.scenario_dt)."""
    parts = []
    for (scenario, env), g in records.groupby(["scenario", "env"], sort=True):
        per = episode_metrics(g, scenario_dt(env) if dt is None else dt)
        s = summarize(per, by=["algorithm"])
        parts.append(s.assign(scenario=scenario, env=env))
    out = pd.concat(parts, ignore_index=True)
    return success_rates(out)


# -- what the report (eval/reporting/report.py) reads -------------------------------------
def reference_rows(plan: ProtocolPlan, policies: Sequence[str],
                   progress: Callable[[str], None] | None = None) -> pd.DataFrame:
    """The reference policies of eval.testing.validity (the continuous and discrete autopilots, the
    safe non-turner, random and the degenerate policies) under the plan's Scenario 1
    conditions: same environments, AC count, steps and episodes."""
    from eval.testing import validity

    frames = []
    for env_name in plan.envs:
        rows = validity.check_scenario(env_name, plan.agents, plan.episodes, plan.steps,
                                       policies=tuple(policies))
        frames.append(validity.summarize(rows).reset_index().assign(env=env_name))
        if progress:
            progress(f"{env_name} references")
    return pd.concat(frames, ignore_index=True)


__all__ = ["EnvPolicies", "METRICS", "ProtocolJob", "ProtocolPlan", "ReferencePolicies",
           "SAMPLED", "TrainedPolicies", "action_repeat_of", "cross_env", "drive",
           "env_policy_factory", "find_checkpoints", "frame_stack_of", "load_for_slot",
           "metrics_table", "obs_of", "policy_factory", "protocol_jobs", "reference_rows",
           "rules", "run_env", "run_job", "run_of", "run_protocol", "slot_checkpoint",
           "slot_order", "slot_summary", "slot_table", "slots_markdown", "trained_env"]
