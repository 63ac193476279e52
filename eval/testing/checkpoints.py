"""Which checkpoint represents each algorithm in a test (the test protocol,
eval/testing/protocol.py): the newest run of each algorithm under ``--runs``
(:func:`find_checkpoints`), the AC a run trained in a slot (:func:`slot_checkpoint`), the
environment a run trained in, and the checkpoints that drive another environment than theirs
(:func:`cross_env`). Which AC represents a run is eval/testing/selection.py's rule."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from eval.testing import selection
from eval.testing.protocol import ProtocolError


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

