"""The run folder: its layout, config.yaml, manifest.json, the lock, and checkpoint recovery.

A run (eval/training/trainer.py) lives in ``runs/<env>__<algo>__<seed>__<timestamp>/``:

    config.yaml        the resolved configuration (what `--resume` reads back)
    manifest.json      package versions, git commit, seeds, hashes of the SUMO/scenario files
                       (and of the frozen encoder, with --encoder)
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

episodes.csv, TensorBoard and the checkpoints themselves are written by
:class:`eval.training.runlog.RunLog`.

Disk (``--keep``, :data:`KEEP_POLICIES`): ``latest.pt`` holds everything resuming
needs (weights, optimizer moments, target networks), ``best.pt`` only the policy the
test drives (agents/checkpoint.py). While a run is unfinished both stay; once it
reaches its step budget, ``--keep best`` (the CLI's default) deletes each AC's
``latest.pt``, so a finished run holds one policy file per AC, and ``--keep all``
keeps it (to train further from it, or for PBT, whose trials clone each other's
``latest.pt``).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import fcntl
import hashlib
import json
import logging
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from eval.testing import files
from eval.training.config import ALGORITHMS, OBS_VARIANTS, TrainConfig, TrainError

log = logging.getLogger(__name__)


def unwritable_reason(folder: Path) -> str | None:
    """Create `folder` and write a probe file in it: None if that works, else why not.
    Output folders are checked this way before any work, so a bad --out fails at once."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write-test-{os.getpid()}"
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        return str(exc.strerror or exc)
    return None


def new_run_dir(out: Path, cfg: TrainConfig, keep: str | None = None) -> Path:
    """Create ``out/<env>__<algo>__<seed>__<timestamp>/`` with its config.yaml (``keep``: the
    run's ``--keep``, recorded there) and manifest.json; fail early if unwritable."""
    out = Path(out)
    reason = unwritable_reason(out)
    if reason:
        raise TrainError(f"cannot write to output folder {out}: {reason}; choose another --out")
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    env = Path(cfg.env).stem  # a scenario given by path: name the folder after the file
    run = out / f"{env}__{cfg.algo}__{cfg.seed}__{stamp}"
    suffix = 1
    while run.exists():
        run = out / f"{env}__{cfg.algo}__{cfg.seed}__{stamp}-{suffix}"
        suffix += 1
    (run / "checkpoints").mkdir(parents=True)
    write_run_config(run, cfg, keep)
    atomic_write(run / "manifest.json", json.dumps(manifest(cfg), indent=2))
    return run


def write_run_config(run: Path, cfg: TrainConfig, keep: str | None = None) -> None:
    """config.yaml: ``cfg`` and, beside its keys, ``keep`` (the run's ``--keep``, what a resume
    honours; :func:`run_keep`). ``keep`` None keeps the file's own (or writes none)."""
    keep = keep if keep is not None else run_keep(run)
    data = cfg.to_dict() | ({"keep": keep} if keep is not None else {})
    atomic_write(Path(run) / "config.yaml", yaml.safe_dump(data, sort_keys=False))


def run_keep(run: Path) -> str | None:
    """The ``--keep`` policy a run's config.yaml records; None for a run written before it
    was recorded, or without a readable config.yaml (:func:`load_run_config` names that)."""
    try:
        data = yaml.safe_load((Path(run) / "config.yaml").read_text())
    except (OSError, yaml.YAMLError, UnicodeDecodeError):
        return None
    keep = data.get("keep") if isinstance(data, dict) else None
    return keep if keep in KEEP_POLICIES else None


def resume_keep(run: Path, given: str) -> str:
    """The ``--keep`` a resumed run finishes with: ``all`` where the run was started with it or
    the resume asks for it (the one that deletes less: a resume never prunes what the run was
    told to keep), else ``best``."""
    return "all" if "all" in (run_keep(run), given) else given


def extend_budget(run: Path, cfg: TrainConfig, done: int, steps: int) -> TrainConfig:
    """``cfg`` with its budget raised to ``steps`` environment steps, written to the run's
    config.yaml (``cosim train --resume RUN --steps N``: train a run further; later resumes
    keep the new budget). Lowering it is refused, and so is extending a finished run whose
    ACs kept only best.pt (``--keep best``): training on needs every AC's latest.pt.

    Raises:
        TrainError: ``steps`` below the steps done, or an AC without latest.pt.
    """
    if steps < max(done, cfg.steps):
        raise TrainError(f"--steps {steps} is below the {max(done, cfg.steps)} env steps {run} already "
                         f"has as its budget; give a larger --steps to train it further")
    if steps == cfg.steps:
        return cfg
    missing = [ac.name for ac in sorted((run / "checkpoints").iterdir())
               if ac.is_dir() and not (ac / "latest.pt").exists()] if done >= cfg.steps else []
    if missing:
        raise TrainError(f"{run} is finished and kept only best.pt for {', '.join(missing)} (--keep best); "
                         "training it further needs latest.pt: train runs you will extend with --keep all")
    cfg = dataclasses.replace(cfg, steps=int(steps))
    write_run_config(run, cfg)
    return cfg


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
    keep = data.pop("keep", None)  # the run's --keep (write_run_config), not a TrainConfig key
    if keep is not None and keep not in KEEP_POLICIES:
        raise TrainError(f"{path}: 'keep' must be one of {', '.join(sorted(KEEP_POLICIES))}, got {keep!r}; {fix}")
    fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise TrainError(f"{path}: unknown key(s) {unknown}; valid keys: {sorted(fields)}")
    if data.get("algo") not in ALGORITHMS:
        raise TrainError(f"{path}: 'algo' must be one of {', '.join(ALGORITHMS)}, got {data.get('algo')!r}")
    for key, f in fields.items():
        if key not in data or key == "algo":
            continue
        kind = dict if key == "agent_config" else {"int": int, "str": str, "bool": bool}.get(str(f.type), object)
        value = data[key]
        if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
            raise TrainError(f"{path}: '{key}' must be {kind.__name__}, got {value!r}; {fix}")
    try:  # builds agent_config, the algorithm's typed config, from its mapping (checking each key)
        cfg = TrainConfig(**data)
    except TrainError as exc:
        raise TrainError(f"{path}: {exc}") from None
    if cfg.obs not in OBS_VARIANTS:
        raise TrainError(f"{path}: 'obs' must be {' or '.join(OBS_VARIANTS)}, got {cfg.obs!r}; {fix}")
    if min(cfg.agents, cfg.steps, cfg.horizon, cfg.checkpoint_every, cfg.workers, cfg.image_size) < 1:
        raise TrainError(f"{path}: agents, steps, horizon, checkpoint_every, workers and image_size "
                         f"must be >= 1; {fix}")
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
    from cosim.scenario import load_scenario

    sc = load_scenario(cfg.env)
    files = [sc.source, sc.net, *sc.demand, *sc.pedestrian_demand, *sc.additional]
    return {
        "created": dt.datetime.now(dt.UTC).isoformat(),
        **software(),
        "seeds": {"run": cfg.seed, "agents": {f"ac_{k}": cfg.seed + k for k in range(cfg.agents)}},
        "files_sha256": {str(p.name): hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in files},
        # the frozen perception encoder the ACs learn on (--encoder), by its file's hash
        **({"encoder": {"path": cfg.encoder, "sha256": cfg.encoder_sha256}} if cfg.encoder else {}),
    }


PACKAGES = ("cosim", "torch", "numpy", "eclipse-sumo", "libsumo", "pybullet", "gymnasium",
            "pettingzoo", "pandas")
"""The distributions whose versions a run's manifest and a report's provenance record."""


def software(command: str | None = None) -> dict[str, Any]:
    """What ran: the command line (default: this process's), the task's version
    (``cosim.TASK_VERSION``), Python, the platform, the CPU (:func:`cpu_model`), the
    versions of :data:`PACKAGES` (None: not installed), :func:`git_commit` now and
    :data:`GIT_AT_START` (the code this process loaded; a study's process can outlive a commit). The one
    builder of this part of a run's ``manifest.json`` and a report's ``provenance.json``."""
    from importlib import metadata

    versions = {}
    for pkg in PACKAGES:
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    from cosim import TASK_VERSION

    return {
        "command": command if command is not None else " ".join(sys.argv),
        "task_version": TASK_VERSION,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "versions": versions,
        "git": git_commit(),
        "git_at_start": GIT_AT_START,
    }


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str | None:
    """The CPU's model name (Linux's ``cpuinfo``, else ``platform.processor()``; None when
    neither says): torch's float results differ between CPUs (MKL's vector math, docs/design.md),
    so a run's weights repeat bit for bit only on a CPU of the same kind."""
    try:
        for line in cpuinfo.read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or None


def git_commit() -> dict[str, Any] | None:
    """The checkout's commit, and whether a tracked file differs from it (``dirty``; untracked
    files such as run folders do not count); None outside a git checkout."""
    root = Path(__file__).resolve().parent.parent
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                                text=True, check=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, check=True, timeout=10).stdout.strip()
        return {"commit": commit, "dirty": bool(dirty)}
    except (OSError, subprocess.SubprocessError):
        return None


GIT_AT_START = git_commit()
"""The checkout's commit when this process imported this module: the code it runs. A process
that lives across commits (a study's driver, for hours) writes provenance naming the commit of
the moment (``git``) and this one (``git_at_start``)."""


def atomic_write(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` so a reader sees the old file or the new, never half
    (eval/testing/files.py ``atomic_write``).

    Raises:
        TrainError: the file could not be written, naming it, the reason and the fix.
    """
    files.atomic_write(path, text, write_error)


def write_error(path: Path, exc: OSError) -> TrainError:
    """The one-line error of a write to ``path`` that failed with ``exc``: what failed, why, the
    free space there, and what to do (a full disk: free space, then resume; training runs
    resume from their last checkpoint)."""
    return TrainError(files.write_message(
        path, exc, "a training run continues from its last checkpoint with `cosim train --resume RUN`"))


def pending_name(name: str, env_step: int) -> str:
    """``latest.pt`` -> ``latest.pending-<env_step>.pt``: a checkpoint file not yet committed."""
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


def read_state(run: Path) -> dict | None:
    """The progress state.json committed at the last checkpoint; None before the first.

    Raises:
        TrainError: state.json is unreadable (naming the file and the fix).
    """
    path = Path(run) / "state.json"
    if not path.exists():
        return None
    try:
        state = json.loads(path.read_text())
        int(state["env_steps"]), int(state["csv_rows"])
    except (ValueError, KeyError, TypeError) as exc:
        raise TrainError(f"{path} is unreadable ({type(exc).__name__}: {exc}); delete it to restart "
                         "the run from step 0, or start a new run") from None
    return state


def output_folder(path: Path, flag: str) -> Path:
    """Create `path` (a folder for results) now, so a bad --out fails before any work."""
    from cosim.errors import OptionError

    reason = unwritable_reason(path)
    if reason:
        raise OptionError(f"{flag} {path}: cannot write there ({reason}); choose another {flag}")
    return path


KEEP_POLICIES = {
    "best": "a finished run keeps each AC's best.pt (the policy the test drives) and drops latest.pt",
    "all": "a finished run keeps latest.pt too (optimizer and target networks: to train it further)",
}
"""``--keep``: what a run folder keeps once its step budget is reached (module docstring)."""


def prune_finished(run: Path, keep: str) -> int:
    """Apply the ``keep`` policy to a finished run folder; return the bytes freed.

    ``best``: every AC's ``latest.pt`` goes where its ``best.pt`` exists (an AC
    without one keeps its ``latest.pt``: nothing the test can load is deleted).

    Raises:
        ValueError: ``keep`` is not one of :data:`KEEP_POLICIES`.
    """
    if keep not in KEEP_POLICIES:
        raise ValueError(f"keep={keep!r} is not a keep policy; choose one of {sorted(KEEP_POLICIES)}")
    freed = 0
    if keep == "best":
        for folder in sorted((Path(run) / "checkpoints").glob("*")):
            latest, best = folder / "latest.pt", folder / "best.pt"
            if latest.is_file() and best.is_file():
                freed += latest.stat().st_size
                latest.unlink()
    return freed
