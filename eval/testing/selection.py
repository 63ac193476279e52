"""Which AC of a training run represents its algorithm in the test (issue 13).

A run trains N ACs of one algorithm; the test drives one per algorithm and slot. A
slot the run trained an AC in is driven by that AC (eval/testing/checkpoints.py, slot_checkpoint:
the camera has no route command, an AC knows only its own route); every other slot, and
the report's "checkpoint tested" line, use the AC chosen by this rule:

1. Each AC's ``best.pt`` is saved when its validation score (mean return, or mean driving
   score under ``--select-by ds``, over held-out episodes under the test's rules,
   eval/training/validation.py; docs/task.md, "Checkpoint selection") reaches a new high, or, in runs without validation, the mean return of its
   last 20 training episodes (eval/training/runlog.py, RunLog.checkpoint); ``state.json`` keeps
   that score per AC (``best``) and ``selection.json`` says which basis. The AC with the
   highest score represents the run, with its ``best.pt``.
2. A run without those scores (interrupted before its first checkpoint, or older):
   the AC with the highest mean return over its last 20 episodes in ``episodes.csv``.
3. Neither: ``ac_0``.

Ties go to the lowest AC index; an AC without a checkpoint file is never chosen.
``best.pt`` is taken when it exists, else ``latest.pt``. ``cosim test --checkpoint
ALGO=PATH`` overrides the rule for that algorithm. The rule and the scores are
written into the report (index.md / index.html, provenance.json).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

RULE = ("highest best-checkpoint score in state.json (the AC's validation score under the "
        "test's rules when selection.json says basis validation, else the mean return of its last 20 "
        "training episodes when best.pt was saved); else highest mean return over the "
        "last 20 episodes in episodes.csv; else ac_0; ties to the lowest index")
WINDOW = 20


@dataclass(frozen=True)
class Selection:
    path: Path
    ac: str
    basis: str                      # "state.json best", "episodes.csv last 20", "ac_0 default", "given"
    scores: dict = field(default_factory=dict)


def checkpoint_of(run: Path, ac: str) -> Path | None:
    """``ac``'s checkpoint in ``run``: best.pt, else latest.pt, else None."""
    for name in ("best.pt", "latest.pt"):
        p = run / "checkpoints" / ac / name
        if p.exists():
            return p
    return None


def _index(ac: str) -> int:
    try:
        return int(ac.split("_")[1])
    except (IndexError, ValueError):
        return 10**6


def choose(run: Path) -> Selection | None:
    """The AC representing the run (module rule); None when the run has no checkpoint."""
    run = Path(run)
    acs = sorted((p.name for p in (run / "checkpoints").glob("ac_*") if p.is_dir()), key=_index)
    acs = [a for a in acs if checkpoint_of(run, a) is not None]
    if not acs:
        return None
    scores: dict[str, float] = {}
    basis = ""
    try:
        best = json.loads((run / "state.json").read_text()).get("best", {})
        scores = {a: float(best[a]) for a in acs if a in best}
        basis = "state.json best"
        record = run / "selection.json"
        if record.exists() and json.loads(record.read_text()).get("basis") == "validation":
            basis = "state.json best (validation)"
    except (OSError, ValueError, TypeError):
        scores = {}
    if not scores:
        try:
            eps = pd.read_csv(run / "episodes.csv")
            scores = {a: float(g["return"].tail(WINDOW).mean())
                      for a, g in eps.groupby("agent") if a in acs and len(g)}
            basis = f"episodes.csv last {WINDOW}"
        except (OSError, ValueError, KeyError, pd.errors.EmptyDataError):
            scores = {}
    if scores:
        ac = max(scores, key=lambda a: (scores[a], -_index(a)))
    else:
        ac, basis = acs[0], "ac_0 default" if acs[0] == "ac_0" else "first AC"
    return Selection(checkpoint_of(run, ac), ac, basis, {k: round(v, 4) for k, v in scores.items()})


def describe(path: Path) -> Selection:
    """A checkpoint given on the command line: which run and AC it comes from, if any."""
    path = Path(path)
    ac = path.parent.name if path.parent.name.startswith("ac_") else "?"
    return Selection(path, ac, "given (--checkpoint)")
