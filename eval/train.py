"""Training runs (SPEC §6, "Scenario 1, train"): N ACs of ONE algorithm, each with its
own network, learning together in a driving environment among background cars.

A run lives in ``runs/<env>__<algo>__<seed>__<timestamp>/``:

    config.yaml        the resolved configuration (what `--resume` reads back)
    manifest.json      package versions, git commit, seeds, hashes of the SUMO/scenario files
    episodes.csv       one row per AC per finished episode: return, length, reward-term sums,
                       event counts, mean speed, DISTANCE, goal
    tb/                TensorBoard scalars: charts/, losses/, driving/, time/
    checkpoints/<ac>/latest.pt, best.pt    self-describing agent checkpoints
    state.json         progress at the last checkpoint (steps, episodes, CSV rows)
    convergence.png    mean episodic reward against env steps, per AC and mean
    run.lock           held (fcntl.flock) by the process training the run; holds its PID

Resuming (``cosim train --resume DIR``) reloads the latest checkpoints, cuts the CSV
back to the rows written before that checkpoint and purges later TensorBoard
events, so an interrupted run (even by kill -9) continues without gaps or
duplicates, losing at most one checkpoint interval. A run interrupted before its
first checkpoint restarts from step 0. A checkpoint is committed in two phases:
every AC's file is written as ``<name>.pending-<step>.pt``, then ``state.json``
(the commit point) is replaced, then the pending files are renamed; a resume
rolls forward the pending files of the committed step and deletes any others,
so an interruption at any moment leaves the agents and state.json consistent.
One process at a time trains a run folder (``run.lock``); a second is refused
naming the PID that holds it. Replay buffers are not
checkpointed (they would be gigabytes of images): an off-policy agent refills its
buffer after a resume.

PPO, DQN, DDPG and TD3 step ``--envs N`` environments through
:func:`agents.loop.run_vector_loop`: one in this process, or N worker processes
(``agents/vector.py``), each AC acting in all of them in one forward pass; each
environment's episodes become CSV rows. A3C and IMPALA run worker/actor
processes, each with its own environment (libsumo allows one simulation per process).
"""

from __future__ import annotations

import csv
import dataclasses
import datetime as dt
import fcntl
import functools
import hashlib
import json
import logging
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cosim.env import EPISODE_EVENTS, EPISODE_INFO
from cosim.errors import CosimError
from cosim.events import REWARD_TERMS

log = logging.getLogger(__name__)

ALGORITHMS = ("ppo", "a3c", "impala", "dqn", "ddpg", "td3")
DISCRETE_ALGOS = ("ppo", "a3c", "impala", "dqn")
CONTINUOUS_ALGOS = ("ddpg", "td3")
ASYNC_ALGOS = ("a3c", "impala")


class TrainError(CosimError, ValueError):
    """A training request that cannot run; the message says what to change."""


@dataclass(frozen=True)
class TrainPreset:
    """Budgets and sizes of a family of runs."""

    steps: dict[str, int]
    """Environment steps per algorithm."""
    agents: int
    """Learning cars trained together."""
    horizon: int
    """Steps per episode before truncation."""
    checkpoint_every: int
    """Environment steps between checkpoints."""
    agent_preset: str
    """The agents' hyperparameter preset ("default" or "paper")."""
    workers: int
    """Worker/actor processes for A3C and IMPALA."""
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Per-algorithm hyperparameter changes on top of agent_preset."""
    reward_scale: float = 0.01
    """Every algorithm learns on reward x this: the driving reward is worth up to ~24
    per step and -50 per collision, so unscaled returns run to thousands and the value
    loss swamps the policy's gradients in the shared CNN (PPO collapsed without it)."""


# DDPG and TD3 in the quick preset. From pixels the deterministic actor ran into a bound
# (full steer) and stuck there at lr 1e-3; a slower actor, the pre-tanh penalty and
# gentler noise learn to drive env_1 (README, Training).
_QUICK_ACTOR_CRITIC = {"learning_starts": 500, "buffer_size": 20_000, "batch_size": 64, "train_freq": 4,
                       "exploration_noise": 0.1, "actor_learning_rate": 1e-4, "pre_tanh_penalty": 0.1}

PRESETS: dict[str, TrainPreset] = {
    # CI: the whole six-algorithm run in about three minutes on two cores.
    "smoke": TrainPreset(
        steps=dict.fromkeys(ALGORITHMS, 120), agents=2, horizon=60, checkpoint_every=40,
        agent_preset="default", workers=1,
        overrides={
            "ppo": {"rollout_steps": 32, "batch_size": 16, "epochs": 1},
            "dqn": {"learning_starts": 32, "batch_size": 16, "buffer_size": 1000,
                    "exploration_steps": 100, "train_freq": 4},
            "ddpg": {"learning_starts": 32, "batch_size": 16, "buffer_size": 1000, "train_freq": 4},
            "td3": {"learning_starts": 32, "batch_size": 16, "buffer_size": 1000, "train_freq": 4},
            "a3c": {"n_steps": 10},
            "impala": {"unroll_length": 10, "batch_size": 1},
        },
    ),
    # Each algorithm about 5-10 minutes on two cores.
    "quick": TrainPreset(
        steps={"ppo": 30_000, "a3c": 60_000, "impala": 60_000, "dqn": 12_000,
               "ddpg": 10_000, "td3": 10_000},
        agents=3, horizon=300, checkpoint_every=2_000, agent_preset="default", workers=2,
        overrides={
            "ppo": {"rollout_steps": 512, "batch_size": 64, "epochs": 4, "ent_coef": 0.01},
            "dqn": {"learning_starts": 500, "buffer_size": 20_000, "exploration_steps": 5_000,
                    "target_update_interval": 500, "batch_size": 32, "gradient_steps": 1},
            "ddpg": _QUICK_ACTOR_CRITIC,
            "td3": _QUICK_ACTOR_CRITIC,
        },
    ),
    # SPEC §5 budgets: 600-800 episodes, ~1.2 M steps per algorithm, Table 3 hyperparameters.
    "paper": TrainPreset(
        steps=dict.fromkeys(ALGORITHMS, 1_200_000), agents=3, horizon=2_000,
        checkpoint_every=20_000, agent_preset="paper", workers=2,
    ),
}


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (written to config.yaml)."""

    algo: str
    env: str = "env_1"
    agents: int = 3
    steps: int = 10_000
    seed: int = 0
    preset: str = "quick"
    horizon: int = 300
    checkpoint_every: int = 2_000
    workers: int = 2
    image_size: int = 84
    agent_config: dict[str, Any] = field(default_factory=dict)
    envs: int = 1
    """Environments stepped together, each in its own process when > 1 (PPO, DQN, DDPG, TD3)."""
    device: str = "auto"
    """Torch device of the learners: auto (cuda when available), cpu or cuda."""
    torch_threads: int = 0
    """torch.set_num_threads in the trainer; 0: the CPUs left beside the env workers
    (cpu_count - envs, at least 1) when envs > 1, else torch's default."""

    @property
    def action_type(self) -> str:
        return "discrete" if self.algo in DISCRETE_ALGOS else "continuous"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def make_config(algo: str, env: str = "env_1", preset: str = "quick", *, agents: int | None = None,
                steps: int | None = None, seed: int = 0, action_type: str | None = None,
                image_size: int = 84, agent_preset: str | None = None,
                hyper: Mapping[str, str] | None = None, envs: int = 1, device: str = "auto",
                torch_threads: int = 0) -> TrainConfig:
    """Resolve a training request into a TrainConfig, refusing what cannot work.

    ``hyper`` changes agent hyperparameters last, field name -> value as text
    (``cosim train --set actor_learning_rate=1e-4``).

    Raises:
        TrainError: unknown algorithm or preset (listing the valid ones), an action
            type the algorithm cannot use (with the reason), bad numbers.
        cosim.errors.ScenarioError: unknown environment (listing the valid ones).
    """
    from agents.registry import get_agent_class
    from cosim.scenario import load_scenario

    if algo not in ALGORITHMS:
        raise TrainError(f"unknown algorithm {algo!r}; choose one of {', '.join(ALGORITHMS)} (or 'all')")
    if preset not in PRESETS:
        raise TrainError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    natural = "discrete" if algo in DISCRETE_ALGOS else "continuous"
    if action_type is not None and action_type != natural:
        why = ("it picks among a finite set of actions (Discrete(9))" if natural == "discrete"
               else "its actor outputs continuous values (Box(-1, 1, (2,)))")
        raise TrainError(
            f"{algo} cannot train with {action_type} actions: {why}; use --action-type {natural} "
            f"or a {'continuous' if natural == 'discrete' else 'discrete'} algorithm "
            f"({', '.join(CONTINUOUS_ALGOS if natural == 'discrete' else DISCRETE_ALGOS)})"
        )
    scenario = load_scenario(env)
    p = PRESETS[preset]
    n = p.agents if agents is None else int(agents)
    if not 1 <= n <= scenario.max_agents:
        raise TrainError(f"--agents must be 1..{scenario.max_agents} for {env}, got {n}")
    total = p.steps[algo] if steps is None else int(steps)
    if total < 1:
        raise TrainError(f"--steps must be >= 1, got {total}")
    if int(envs) < 1 or int(torch_threads) < 0:
        raise TrainError(f"--envs must be >= 1 and --torch-threads >= 0, got {envs} and {torch_threads}")
    if int(envs) > 1 and algo in ASYNC_ALGOS:
        raise TrainError(f"--envs applies to ppo, dqn, ddpg and td3; {algo} runs one environment per "
                         "worker process (the preset's workers)")
    if device not in ("auto", "cpu", "cuda"):
        raise TrainError(f"--device must be auto, cpu or cuda, got {device!r}")
    config_cls = get_agent_class(algo).config_class
    chosen = agent_preset or p.agent_preset
    try:
        base = config_cls.preset(chosen, **{"reward_scale": p.reward_scale, **p.overrides.get(algo, {})})
        agent_config = base.replace(**parse_hyper(base.to_dict(), hyper or {}, algo)).to_dict()
    except ValueError as exc:
        raise TrainError(f"{algo} hyperparameters: {exc}") from exc
    return TrainConfig(
        algo=algo, env=env, agents=n, steps=total, seed=int(seed), preset=preset,
        horizon=p.horizon, checkpoint_every=min(p.checkpoint_every, total), workers=p.workers,
        image_size=int(image_size), agent_config=agent_config, envs=int(envs), device=device,
        torch_threads=int(torch_threads),
    )


def parse_set(items: list[str]) -> dict[str, str]:
    """``["lr=3e-4", ...]`` (``--set`` arguments) -> ``{"lr": "3e-4"}``; values stay text."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise TrainError(f"--set {item!r}: write FIELD=VALUE, e.g. --set learning_rate=3e-4")
        out[key.strip()] = value.strip()
    return out


def parse_hyper(current: Mapping[str, Any], hyper: Mapping[str, str], algo: str) -> dict[str, Any]:
    """Typed values for hyperparameter overrides given as text, checked against ``current``.

    A value must have the type of the field's current value; ints are accepted for
    floats and lists for tuples. (YAML reads "1e-4" as text, hence float().)

    Raises:
        ValueError: an unknown field (listing the valid ones) or a value of the wrong type.
    """
    out: dict[str, Any] = {}
    for key, text in hyper.items():
        if key not in current:
            raise ValueError(f"--set {key}: {algo} has no such hyperparameter; valid: {', '.join(sorted(current))}")
        old = current[key]
        try:
            value = yaml.safe_load(text)
            if isinstance(old, float) and not isinstance(value, bool):
                value = float(value)
            elif isinstance(old, tuple) and isinstance(value, list):
                value = tuple(value)
            ok = type(value) is type(old)
        except (TypeError, ValueError, yaml.YAMLError):
            ok = False
        if not ok:
            kind = type(old).__name__
            raise ValueError(
                f"--set {key}={text}: expected {'an' if kind[0] in 'aeiou' else 'a'} {kind} like {old!r}"
            )
        out[key] = value
    return out


# -- run folder -------------------------------------------------------------------
def new_run_dir(out: Path, cfg: TrainConfig) -> Path:
    """Create ``out/<env>__<algo>__<seed>__<timestamp>/``; fail early if unwritable."""
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-test-{os.getpid()}"
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise TrainError(f"cannot write to output folder {out}: {exc.strerror or exc}; "
                         "choose another --out") from exc
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    env = Path(cfg.env).stem  # a scenario given by path: name the folder after the file
    run = out / f"{env}__{cfg.algo}__{cfg.seed}__{stamp}"
    suffix = 1
    while run.exists():
        run = out / f"{env}__{cfg.algo}__{cfg.seed}__{stamp}-{suffix}"
        suffix += 1
    (run / "checkpoints").mkdir(parents=True)
    _atomic_write(run / "config.yaml", yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    _atomic_write(run / "manifest.json", json.dumps(manifest(cfg), indent=2))
    return run


def load_run_config(run: Path) -> TrainConfig:
    """The TrainConfig in a run folder's config.yaml, checked key by key.

    Raises:
        TrainError: no config.yaml, malformed YAML, unknown or missing keys, values
            of the wrong type; the message names the file and the key.
    """
    path = Path(run) / "config.yaml"
    if not path.exists():
        raise TrainError(f"{run} is not a training run folder (no config.yaml); pass runs/<dir>")
    fix = "restore it (the values used are also in manifest.json's command) or start a new run"
    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        where = getattr(exc, "problem_mark", None)
        at = f" at line {where.line + 1}" if where is not None else ""
        raise TrainError(f"{path}: malformed YAML{at}; {fix}") from None
    if not isinstance(data, dict):
        raise TrainError(f"{path}: expected a mapping of run settings, got {type(data).__name__}; {fix}")
    fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise TrainError(f"{path}: unknown key(s) {unknown}; valid keys: {sorted(fields)}")
    if data.get("algo") not in ALGORITHMS:
        raise TrainError(f"{path}: 'algo' must be one of {', '.join(ALGORITHMS)}, got {data.get('algo')!r}")
    for key, f in fields.items():
        if key not in data or key == "algo":
            continue
        kind = {"int": int, "str": str, "dict[str, Any]": dict}.get(str(f.type), object)
        value = data[key]
        if not isinstance(value, kind) or isinstance(value, bool):
            raise TrainError(f"{path}: '{key}' must be {kind.__name__}, got {value!r}; {fix}")
    cfg = TrainConfig(**data)
    if min(cfg.agents, cfg.steps, cfg.horizon, cfg.checkpoint_every, cfg.workers, cfg.image_size) < 1:
        raise TrainError(f"{path}: agents, steps, horizon, checkpoint_every, workers and image_size "
                         f"must be >= 1; {fix}")
    from agents.registry import get_agent_class

    try:
        get_agent_class(cfg.algo).config_class.from_dict(cfg.agent_config)
    except (TypeError, ValueError) as exc:
        raise TrainError(f"{path}: 'agent_config': {exc}") from None
    return cfg


class RunLock:
    """Exclusive use of a run folder by one process: ``fcntl.flock`` on ``run.lock``.

    The file holds the owner's PID so a refused process can name it. The kernel
    releases a flock when its process dies (even by kill -9), so a lock left by a
    dead process is simply taken over; the file itself stays (unlinking a lock file
    races with a process that just opened it).
    """

    def __init__(self, run: Path):
        self.path = Path(run) / "run.lock"
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = self._holder(fd)
            os.close(fd)
            raise TrainError(
                f"run {run} is in use by process {holder} (see {self.path}); wait for it to "
                "finish or stop it, then resume"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self.fd: int | None = fd

    @staticmethod
    def _holder(fd: int) -> str:
        for _ in range(20):  # the holder writes its PID right after locking
            pid = os.pread(fd, 32, 0).decode(errors="replace").strip()
            if pid:
                return f"PID {pid}"
            time.sleep(0.05)
        return "with an unknown PID"

    def release(self) -> None:
        if self.fd is not None:
            os.ftruncate(self.fd, 0)
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None


def manifest(cfg: TrainConfig) -> dict[str, Any]:
    """Reproducibility record: versions, git commit, seeds, hashes of the inputs."""
    from importlib import metadata

    from cosim.scenario import load_scenario

    sc = load_scenario(cfg.env)
    files = [sc.source, sc.net, *sc.demand, *sc.pedestrian_demand, *sc.additional]
    versions = {}
    for pkg in ("cosim", "torch", "numpy", "eclipse-sumo", "libsumo", "pybullet", "gymnasium",
                "pettingzoo", "pandas"):
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    return {
        "created": dt.datetime.now(dt.UTC).isoformat(),
        "command": " ".join(sys.argv),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "versions": versions,
        "git": _git_commit(),
        "seeds": {"run": cfg.seed, "agents": {f"ac_{k}": cfg.seed + k for k in range(cfg.agents)}},
        "files_sha256": {str(p.name): hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in files},
    }


def _git_commit() -> dict[str, Any] | None:
    root = Path(__file__).resolve().parent.parent
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                                text=True, check=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True,
                               text=True, check=True, timeout=10).stdout.strip() != ""
        return {"commit": commit, "dirty": dirty}
    except (OSError, subprocess.SubprocessError):
        return None


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


# derived from the reward-term and event catalogues (cosim.events), so a new term or event
# gets its column without an edit here
EPISODE_FIELDS = [
    "agent", "episode", "env_step", "return", "length", *(f"r_{t}" for t in REWARD_TERMS),
    *(f"n_{e}" for e in EPISODE_EVENTS), "mean_speed_kmh", "DISTANCE", "distance_to_goal",
    "goal_reached", "wall_time_s",
]


class RunLog:
    """The run's CSV, TensorBoard writer and checkpoint bookkeeping."""

    def __init__(self, run: Path, cfg: TrainConfig, resume_state: dict | None):
        from torch.utils.tensorboard import SummaryWriter

        self.run, self.cfg = Path(run), cfg
        self.csv_path = self.run / "episodes.csv"
        state = resume_state or {}
        self.env_steps = int(state.get("env_steps", 0))
        self.episodes = dict(state.get("episodes", {}))
        self.best = dict(state.get("best", {}))
        self.rows = int(state.get("csv_rows", 0))
        self.elapsed0 = float(state.get("elapsed_s", 0.0))
        self.start = time.monotonic()
        self.recent: dict[str, deque] = {f"ac_{k}": deque(maxlen=20) for k in range(cfg.agents)}
        self._truncate_csv(self.rows)
        self._file = open(self.csv_path, "a", newline="")  # noqa: SIM115 - closed in close()
        self._csv = csv.DictWriter(self._file, fieldnames=EPISODE_FIELDS, extrasaction="ignore")
        if self.rows == 0:
            self._csv.writeheader()
            self._file.flush()
        for row in self._read_rows():
            self.recent[row["agent"]].append(float(row["return"]))
        self.tb = SummaryWriter(str(self.run / "tb"), purge_step=self.env_steps or None)
        self.on_checkpoint: Callable[[Path, int, float], None] | None = None

    def _read_rows(self) -> list[dict]:
        with open(self.csv_path, newline="") as f:
            return list(csv.DictReader(f))

    def _truncate_csv(self, rows: int) -> None:
        """Keep the header and the first `rows` rows (those covered by the checkpoint).

        With no rows covered (a run stopped before its first checkpoint) the file is
        removed, header and all, and written afresh.
        """
        if not self.csv_path.exists():
            return
        if rows == 0:
            self.csv_path.unlink()
            return
        with open(self.csv_path, newline="") as f:
            lines = f.readlines()
        kept = lines[: 1 + rows] if lines else []
        if len(kept) != len(lines):
            log.info("resume: dropping %d episode rows written after the last checkpoint",
                     len(lines) - len(kept))
        _atomic_write(self.csv_path, "".join(kept))

    @property
    def elapsed(self) -> float:
        return self.elapsed0 + time.monotonic() - self.start

    def episode(self, agent: str, stats: dict, env_step: int) -> None:
        k = self.episodes.get(agent, 0)
        self.episodes[agent] = k + 1
        row = {**stats, "agent": agent, "episode": k, "env_step": env_step,
               "wall_time_s": round(self.elapsed, 2)}
        self._csv.writerow(row)
        self._file.flush()
        self.rows += 1
        self.recent[agent].append(float(stats["return"]))
        tb = self.tb
        tb.add_scalar(f"charts/episodic_return/{agent}", stats["return"], env_step)
        tb.add_scalar(f"charts/episodic_length/{agent}", stats["length"], env_step)
        tb.add_scalar("charts/mean_recent_return", self.mean_recent(), env_step)
        length = max(stats["length"], 1)
        tb.add_scalar(f"driving/collision_fraction/{agent}",
                      (stats["n_collision_vehicle"] + stats["n_collision_pedestrian"]
                       + stats["n_collision_object"]) / length, env_step)
        tb.add_scalar(f"driving/lane_violation_fraction/{agent}", stats["n_lane_violation"] / length, env_step)
        tb.add_scalar(f"driving/DISTANCE/{agent}", stats["DISTANCE"], env_step)
        tb.add_scalar(f"driving/mean_speed_kmh/{agent}", stats["mean_speed_kmh"], env_step)

    def metrics(self, agent: str, metrics: dict[str, float], env_step: int) -> None:
        for name, value in metrics.items():
            head, _, rest = name.partition("/")
            tag = f"{head}/{rest}/{agent}" if rest else f"{head}/{agent}"
            self.tb.add_scalar(tag, value, env_step)

    def mean_recent(self) -> float:
        values = [v for d in self.recent.values() for v in d]
        return float(np.mean(values)) if values else float("nan")

    def checkpoint(self, agents: dict, env_step: int, extra_time: dict[str, float] | None = None) -> None:
        """Save latest (and best) per AC and the state that makes them resumable.

        Two phases (module docstring): pending files, then state.json, then renames.
        """
        best = dict(self.best)
        staged = []
        for agent_id, agent in agents.items():
            folder = self.run / "checkpoints" / agent_id
            folder.mkdir(parents=True, exist_ok=True)
            names = ["latest.pt"]
            recent = self.recent[agent_id]
            if len(recent) >= 3:
                score = float(np.mean(recent))
                if score > best.get(agent_id, -np.inf):
                    best[agent_id] = score
                    names.append("best.pt")
            elif not (folder / "best.pt").exists():
                names.append("best.pt")
            for name in names:
                pending = folder / _pending_name(name, env_step)
                agent.save(pending)  # itself written to a temporary name and renamed
                staged.append((pending, folder / name))
        state = {"env_steps": env_step, "episodes": self.episodes, "best": best,
                 "csv_rows": self.rows, "elapsed_s": self.elapsed, "timing": extra_time or {}}
        _atomic_write(self.run / "state.json", json.dumps(state, indent=2))  # the commit point
        for pending, final in staged:
            os.replace(pending, final)
        self.env_steps, self.best = env_step, best
        for name, value in (extra_time or {}).items():
            self.tb.add_scalar(name, value, env_step)
        self.tb.flush()
        if self.on_checkpoint is not None:
            self.on_checkpoint(self.run, env_step, self.mean_recent())

    def close(self) -> None:
        self._file.close()
        self.tb.close()


def _pending_name(name: str, env_step: int) -> str:
    stem, _, ext = name.rpartition(".")
    return f"{stem}.pending-{env_step}.{ext}"


_PENDING = re.compile(r"^(?P<stem>\w+)\.pending-(?P<step>\d+)\.pt$")


def recover_checkpoints(run: Path, committed_step: int | None) -> None:
    """Finish or undo a checkpoint that an interruption cut short.

    Pending files of the committed step (state.json was replaced, the renames were
    not all done) are renamed into place; pending files of any other step and
    temporary files are deleted. With no committed checkpoint at all the run
    restarts, so every checkpoint file goes.
    """
    for folder in (Path(run) / "checkpoints").glob("*"):
        if not folder.is_dir():
            continue
        for file in folder.iterdir():
            match = _PENDING.match(file.name)
            if committed_step is None:
                file.unlink()
            elif match and int(match["step"]) == committed_step:
                os.replace(file, folder / f"{match['stem']}.pt")
            elif match or ".tmp" in file.name:
                file.unlink()


# -- environments ---------------------------------------------------------------------
def make_env(cfg_dict: dict, worker_seed: int | None = None):
    """Build the training env of a config (top-level, so worker processes can pickle it)."""
    from cosim.env import CosimParallelEnv

    cfg = TrainConfig(**cfg_dict)
    return CosimParallelEnv(
        cfg.env, num_agents=cfg.agents, action_types=cfg.action_type,
        seed=cfg.seed if worker_seed is None else worker_seed, image_size=cfg.image_size,
        horizon=cfg.horizon, terminate_on_collision=True,
    )


class _EpisodeTap:
    """Forwards a ParallelEnv and hands each agent's final ``info[EPISODE_INFO]`` to a callback."""

    def __init__(self, env, on_episode: Callable[[str, dict], None]):
        self.env, self.on_episode = env, on_episode
        self.env_step = 0  # env steps so far (a vector env: summed over the envs it stepped)

    def __getattr__(self, name):  # reset, agents, spaces, close: the env's own
        return getattr(self.env, name)

    def step(self, actions):
        return self._tap(self.env.step(actions))

    def step_wait(self, *envs):  # a vector env's second half of step (agents/vector.py)
        return self._tap(self.env.step_wait(*envs))

    def _tap(self, out):
        # a vector env gives one info dict per environment
        self.env_step += int(out.stepped.sum()) if hasattr(out, "stepped") else 1
        for infos in (out.infos if hasattr(out, "env_reset") else [out[4]]):
            for agent, info in infos.items():
                if EPISODE_INFO in info:
                    self.on_episode(agent, info[EPISODE_INFO])
        return out


# -- training -------------------------------------------------------------------------
def train(cfg: TrainConfig, out: Path = Path("runs"), *, resume: Path | None = None,
          quiet: bool = False, progress: bool = True,
          on_checkpoint: Callable[[Path, int, float], None] | None = None) -> Path:
    """Run (or resume) one training run; return its folder.

    ``on_checkpoint(run, env_steps, mean_return)`` is called after each committed
    checkpoint (how Ray Tune trials report, eval/benchmark.py and eval/pbt.py).

    Raises:
        TrainError: the run folder is held by another process (naming its PID), or
            its config.yaml / state.json is unreadable (naming the file and the key).
    """
    if resume is not None:
        run = Path(resume)
        cfg = load_run_config(run)
        lock = RunLock(run)
        try:
            state = _read_state(run)
            recover_checkpoints(run, None if state is None else int(state["env_steps"]))
            if state is None:  # stopped before its first checkpoint: start again from step 0
                log.info("resume: %s has no checkpoint yet; restarting it from step 0", run)
                shutil.rmtree(run / "tb", ignore_errors=True)
        except BaseException:
            lock.release()
            raise
    else:
        run = new_run_dir(out, cfg)
        lock = RunLock(run)
        state = None
    try:
        _train_locked(cfg, run, state, quiet, progress, on_checkpoint)
    finally:
        lock.release()
    return run


def _read_state(run: Path) -> dict | None:
    path = run / "state.json"
    if not path.exists():
        return None
    try:
        state = json.loads(path.read_text())
        int(state["env_steps"]), int(state["csv_rows"])
    except (ValueError, KeyError, TypeError) as exc:
        raise TrainError(f"{path} is unreadable ({type(exc).__name__}: {exc}); delete it to restart "
                         "the run from step 0, or start a new run") from None
    return state


def _train_locked(cfg: TrainConfig, run: Path, state: dict | None, quiet: bool, progress: bool,
                  on_checkpoint: Callable[[Path, int, float], None] | None = None) -> None:
    runlog = RunLog(run, cfg, state)
    runlog.on_checkpoint = on_checkpoint
    log.info("training %s on %s with %d ACs for %d steps -> %s", cfg.algo, cfg.env, cfg.agents,
             cfg.steps, run)
    try:
        if runlog.env_steps >= cfg.steps:
            log.info("run %s is already complete (%d steps)", run, runlog.env_steps)
        elif cfg.algo in ASYNC_ALGOS:
            _train_async(cfg, runlog, state is not None, quiet, progress)
        else:
            _train_sync(cfg, runlog, state is not None, quiet, progress)
    finally:
        runlog.close()
        plot_convergence(run)


def _load_or_build(cfg: TrainConfig, run: Path, resumed: bool, obs_space, act_space,
                   device: str = "cpu") -> dict:
    import agents as agents_pkg
    from agents.registry import get_agent_class

    cls = get_agent_class(cfg.algo)
    config = cls.config_class.from_dict(cfg.agent_config)
    out = {}
    for k in range(cfg.agents):
        aid = f"ac_{k}"
        latest = run / "checkpoints" / aid / "latest.pt"
        if resumed and latest.exists():
            out[aid] = agents_pkg.load(latest, device=device)  # saved from any device, loads on any
        else:
            out[aid] = cls.from_spaces(obs_space, act_space, config, seed=cfg.seed + k, device=device)
    return out


def _bar(cfg: TrainConfig, runlog: RunLog, quiet: bool, progress: bool):
    from tqdm import tqdm

    return tqdm(total=cfg.steps, initial=runlog.env_steps, unit="step", dynamic_ncols=True,
                desc=f"{cfg.env} {cfg.algo}", disable=quiet or not progress, smoothing=0.05)


def _report(bar, runlog: RunLog, cfg: TrainConfig, step: int, quiet: bool, last_log: list) -> None:
    mean = runlog.mean_recent()
    bar.set_postfix_str(f"return {mean:8.1f}", refresh=False)
    now = time.monotonic()
    if quiet and now - last_log[0] > 30:
        rate = (step - last_log[1]) / (now - last_log[0])
        last_log[0], last_log[1] = now, step
        print(f"[{cfg.algo} {cfg.env}] step {step}/{cfg.steps} recent mean return {mean:.1f} "
              f"({rate:.0f} steps/s)", flush=True)


def _train_sync(cfg: TrainConfig, runlog: RunLog, resumed: bool, quiet: bool, progress: bool) -> None:
    """PPO, DQN, DDPG, TD3: ``cfg.envs`` environments (worker processes when > 1), one
    batched forward pass per AC per step (agents.loop.run_vector_loop, docs/agents.md)."""
    import torch

    from agents.base import resolve_device
    from agents.loop import run_vector_loop
    from agents.vector import make_vector_env

    n = cfg.envs
    # N env workers keep N cores busy; more torch threads than the cores left only contend
    threads = cfg.torch_threads or (max(1, (os.cpu_count() or 1) - n) if n > 1 else 0)
    if threads:
        torch.set_num_threads(threads)
    try:
        device = resolve_device(cfg.device)
    except ValueError as exc:
        raise TrainError(str(exc)) from None
    start_step = runlog.env_steps
    # env i of N: seed + i (env 0 is the one-env run's env)
    fns = [functools.partial(make_env, cfg.to_dict(), cfg.seed + i) for i in range(n)]
    env = _EpisodeTap(make_vector_env(fns), lambda a, s: runlog.episode(a, s, env.env_step))
    env.env_step = start_step
    last = [start_step]
    bar = _bar(cfg, runlog, quiet, progress)
    last_log = [time.monotonic(), start_step]
    try:
        agent_map = _load_or_build(cfg, runlog.run, resumed, env.observation_space("ac_0"),
                                   env.action_space("ac_0"), device)

        def callback(step: int, stats, metrics) -> bool:
            now = start_step + step
            before, last[0] = last[0], now
            for aid, m in metrics.items():
                runlog.metrics(aid, m, now)
            bar.update(now - before)
            if now // cfg.checkpoint_every > before // cfg.checkpoint_every or now >= cfg.steps:
                runlog.checkpoint(agent_map, now, stats.summary())
            _report(bar, runlog, cfg, now, quiet, last_log)
            return now >= cfg.steps

        # episodes after a resume get fresh seeds: seed + 100003 * (episodes so far)
        first_seed = cfg.seed + 100_003 * sum(runlog.episodes.values())
        run_vector_loop(agent_map, env, total_steps=cfg.steps - start_step, callback=callback,
                        seed=first_seed)
    finally:
        bar.close()
        env.close()


def _train_async(cfg: TrainConfig, runlog: RunLog, resumed: bool, quiet: bool, progress: bool) -> None:
    from agents.registry import get_agent_class

    if cfg.algo == "a3c":
        from agents.a3c import train_a3c as trainer
    else:
        from agents.impala import train_impala as trainer
    probe = make_env(cfg.to_dict())
    obs_space, act_space = probe.observation_space("ac_0"), probe.action_space("ac_0")
    probe.close()
    start_step = runlog.env_steps
    initial = _load_or_build(cfg, runlog.run, resumed, obs_space, act_space) if resumed else None
    config = get_agent_class(cfg.algo).config_class.from_dict(cfg.agent_config)
    bar = _bar(cfg, runlog, quiet, progress)
    last = {"step": start_step, "ckpt": start_step}
    last_log = [time.monotonic(), start_step]

    def callback(p) -> bool:
        now = start_step + int(p.env_steps)
        for ep in p.episodes:
            for aid, stats in getattr(ep, "extras", {}).items():
                runlog.episode(aid, stats, now)
        metrics = p.metrics or {}
        if metrics and all(isinstance(v, dict) for v in metrics.values()):
            for aid, m in metrics.items():  # per-agent metrics
                runlog.metrics(aid, {k: v for k, v in m.items() if np.isscalar(v)}, now)
        elif metrics:  # shared metrics (e.g. policy lag)
            scalars = {k: v for k, v in metrics.items() if np.isscalar(v)}
            for aid in p.agents:
                runlog.metrics(aid, scalars, now)
        bar.update(max(now - last["step"], 0))
        last["step"] = now
        if now - last["ckpt"] >= cfg.checkpoint_every or now >= cfg.steps:
            runlog.checkpoint(p.agents, now)
            last["ckpt"] = now
        _report(bar, runlog, cfg, now, quiet, last_log)
        return now >= cfg.steps

    kwargs = {"num_workers": cfg.workers} if cfg.algo == "a3c" else {"num_actors": cfg.workers}
    if initial is not None:
        kwargs["agents"] = initial
    try:
        trained = trainer(
            functools.partial(make_env, cfg.to_dict()), obs_space, act_space,
            agent_ids=[f"ac_{k}" for k in range(cfg.agents)], config=config,
            total_steps=cfg.steps - start_step, seed=cfg.seed + 7919 * sum(runlog.episodes.values()),
            callback=callback, **kwargs,
        )
        runlog.checkpoint(trained, max(last["step"], runlog.env_steps))
    finally:
        bar.close()


# -- plots --------------------------------------------------------------------------------
def plot_convergence(run: Path, window: int = 10) -> Path | None:
    """Mean episodic reward against env steps, per AC and their mean (the paper's Figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    csv_path = Path(run) / "episodes.csv"
    if not csv_path.exists():
        return None
    df = pd.read_csv(csv_path)
    if df.empty:
        return None
    fig, ax = plt.subplots(figsize=(7, 4))
    curves = []
    for agent, g in df.groupby("agent"):
        g = g.sort_values("env_step")
        smooth = g["return"].rolling(window, min_periods=1).mean()
        ax.plot(g["env_step"], smooth, lw=1, alpha=0.6, label=agent)
        curves.append(pd.Series(smooth.to_numpy(), index=g["env_step"].to_numpy()))
    grid = np.linspace(df["env_step"].min(), df["env_step"].max(), 100)
    mean = np.nanmean([np.interp(grid, c.index, c.to_numpy()) for c in curves], axis=0)
    ax.plot(grid, mean, color="k", lw=2.5, label="mean")
    cfg = yaml.safe_load((Path(run) / "config.yaml").read_text())
    ax.set_title(f"{cfg['algo'].upper()} on {cfg['env']}: convergence ({window}-episode mean)")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episodic reward")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = Path(run) / "convergence.png"
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
