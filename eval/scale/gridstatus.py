"""`cosim benchmark --status`: where a benchmark folder stands, read from its files alone.

A `standard` grid is a day of a 2-core machine and runs across interrupted sessions
(``--resume``); this says, without starting Ray or touching a run, which trials are
finished, which are training now, how far each got, its best validation score so far
and roughly how much trial time is left. Everything comes from the folder
(eval/scale/benchmark.py describes its layout):

- ``benchmark.json``: the plan, hence the cells and their budgets;
- ``runs/<cell>/``: a finished run (moved there when the grid ends);
- ``trials/<cell>/<run>/``: a started trial; its ``state.json``, the last checkpoint (``env_steps``,
  ``elapsed_s``: seconds of learning, and ``best``: each AC's best validation score);
- ``run.lock``: the PID of the process training the run, while it trains.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pandas as pd

from eval.scale.benchmark import BenchmarkPlan, cell_name, load_plan, trial_resources

STATES = ("finished", "training", "stopped", "pending")
"""finished: budget reached; training: a live process holds the run; stopped: started, its
process gone (``--resume`` continues it from ``env_steps``); pending: not started."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def _holder(run: Path) -> int | None:
    """The PID in ``run.lock`` when that process is alive (the lock is truncated on release)."""
    try:
        text = (run / "run.lock").read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() and _alive(int(text)) else None


def _latest_run(folder: Path) -> Path | None:
    """The newest run folder under a trial's folder: one with a config.yaml (it started; its
    state.json appears at its first checkpoint)."""
    runs = sorted(p for p in folder.glob("*") if (p / "config.yaml").exists())
    return runs[-1] if runs else None


RECENT = 10
"""Training episodes per AC that the ``goals`` column averages (the latest)."""


def _recent_goals(run: Path) -> float:
    """The goal rate of each AC's latest :data:`RECENT` training episodes (episodes.csv),
    pooled; NaN before the first episode."""
    try:
        episodes = pd.read_csv(run / "episodes.csv", usecols=["agent", "goal_reached"])
    except (OSError, ValueError, pd.errors.EmptyDataError):  # none yet, or being truncated
        return float("nan")
    recent = episodes.groupby("agent").tail(RECENT)
    return float(recent.goal_reached.astype(float).mean()) if len(recent) else float("nan")


def grid_status(out: Path) -> pd.DataFrame:
    """One row per cell of the saved plan: ``cell, env, algo, seed, cpus, state, env_steps,
    budget, done`` (fraction), ``learning_s`` (seconds of learning so far), ``best`` (the
    highest per-AC validation score so far, NaN before the first validation), ``goals`` (the
    goal rate of each AC's latest training episodes, :func:`_recent_goals`), ``left_s``
    (seconds of learning left at this algorithm's measured rate; NaN when no trial of the
    algorithm has progressed yet), and the ``task_version`` and ``commit`` its run's
    manifest.json records (None before it started)."""
    out = Path(out)
    plan = load_plan(out)
    rows = []
    for cfg in plan.cells():
        name = cell_name(cfg)
        run = out / "runs" / name
        if not (run / "state.json").exists():
            run = _latest_run(out / "trials" / name)
        state = json.loads((run / "state.json").read_text()) if run and (run / "state.json").exists() else {}
        steps = int(state.get("env_steps", 0))
        best = [float(v) for v in (state.get("best") or {}).values()]
        if steps >= cfg.steps:
            what = "finished"
        elif run is None:
            what = "pending"
        else:
            what = "training" if _holder(run) is not None else "stopped"
        goals = _recent_goals(run) if run is not None else float("nan")
        made = json.loads((run / "manifest.json").read_text()) if run and (run / "manifest.json").exists() else {}
        rows.append({"cell": name, "env": cfg.env, "algo": cfg.algo, "seed": cfg.seed,
                     "task_version": made.get("task_version"),
                     "commit": ((made.get("git") or {}).get("commit") or "")[:7] or None,
                     "cpus": trial_resources(cfg, os.cpu_count())["cpu"], "state": what,
                     "env_steps": min(steps, cfg.steps), "budget": cfg.steps,
                     "learning_s": float(state.get("elapsed_s", 0.0)),
                     "best": max(best) if best else float("nan"), "goals": goals})
    table = pd.DataFrame(rows).astype({"task_version": "Int64"})
    table["done"] = table.env_steps / table.budget
    moving = table[(table.env_steps > 0) & (table.learning_s > 0)]
    rate = (moving.env_steps / moving.learning_s).groupby(moving.algo).median()  # env steps/s
    table["left_s"] = (table.budget - table.env_steps) / table.algo.map(rate)
    return table


def _duration(seconds: float) -> str:
    if seconds != seconds:  # NaN
        return "?"
    return f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.0f} min"


def _versions(table: pd.DataFrame, column: str) -> str:
    started = table[column].dropna()
    if started.empty:
        return "-"
    counts = started.value_counts()
    if len(counts) == 1:
        return str(counts.index[0])
    return " and ".join(f"{v} ({n} trial{'s' if n > 1 else ''})" for v, n in counts.items())


def status_text(table: pd.DataFrame, cpus: int | None = None, plan: BenchmarkPlan | None = None) -> str:
    """The table as `cosim benchmark --status` prints it: a heading line (the preset, the
    task version and commit the started trials ran, from their manifests; more than one is
    said), a line per trial, and a closing line: the count per state and the learning time
    left, as the sum over trials and as a wall time on ``cpus`` cores (trials packed by
    their CPUs; validation and start-up not counted)."""
    cpus = cpus or os.cpu_count() or 1
    head = f"preset {plan.preset}, " if plan is not None else ""
    lines = [f"{head}task version {_versions(table, 'task_version')}, commit {_versions(table, 'commit')}",
             f"{'trial':<26} {'state':<9} {'env steps':>17} {'done':>5} {'learning':>9} "
             f"{'best val.':>10} {'goals':>5} {'left':>8}"]
    for r in table.itertuples():
        best = "-" if r.best != r.best else f"{r.best:.0f}"
        left = "" if r.state == "finished" else _duration(r.left_s)
        goals = "-" if r.goals != r.goals else f"{r.goals:.2f}"
        lines.append(f"{r.cell:<26} {r.state:<9} {f'{r.env_steps:,}/{r.budget:,}':>17} "
                     f"{r.done:>5.0%} {_duration(r.learning_s):>9} {best:>10} {goals:>5} {left:>8}")
    counts = table.state.value_counts()
    left = table[table.state != "finished"]
    if left.empty:
        return "\n".join([*lines, f"all {len(table)} trials finished"])
    cpu_s = (left.left_s * left.cpus.clip(upper=cpus)).sum(min_count=1)
    unknown = int(left.left_s.isna().sum())
    tail = f" (+{unknown} trial(s) of algorithms not started yet)" if unknown else ""
    lines.append(", ".join(f"{int(counts.get(s, 0))} {s}" for s in STATES)
                 + f"; learning left: {_duration(left.left_s.sum(min_count=1))} of trial time, "
                 f"~{_duration(cpu_s / cpus)} on {cpus} cores{tail}")
    return "\n".join(lines)
