"""Per-step records: one row per AC per step, the raw material of every metric.

Columns: episode, seed, step, time, agent, algorithm, x, y, heading, speed (m/s),
distance_to_goal, progress, route_completion (the AC-episode's running route completion,
0..1), every event flag (``collision_*``: in contact this step; ``event_*``: a new collision
event starts this step, what the driving score counts), every weighted reward term
(``r_<term>``), reward, n_vehicles, n_pedestrians, spawn/goal coordinates,
terminated, truncated. Stored as Parquet so any other metric can be computed later.
An info without ``route_completion`` or an ``event_*`` flag (an older env) leaves that
column out: the driving score is then NaN (eval/testing/metrics.py).
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from cosim.events import EVENT_FLAGS

EVENT_COLUMNS = (*EVENT_FLAGS, "collision", "lane_violation")
INFO_COLUMNS = (
    "x", "y", "heading", "speed", "distance_to_goal", "progress", "n_vehicles",
    "n_pedestrians", "spawn_x", "spawn_y", "goal_x", "goal_y", "time",
)
SCORE_INFO = ("route_completion",)
"""Float info keys of the driving score, recorded when the info has them."""
OPTIONAL_EVENTS = ("event_vehicle", "event_pedestrian", "event_object")
"""Event flags recorded when the info has them (an env before task version 4 has none)."""


def record_row(*, episode: int, seed: int, step: int, agent: str, algorithm: str,
               info: dict, reward: float, terminated: bool, truncated: bool, **extra) -> dict:
    """One record from an env info dict (see :mod:`cosim.env`)."""
    row = {"episode": episode, "seed": seed, "step": step, "agent": agent, "algorithm": algorithm}
    for key in INFO_COLUMNS:
        row[key] = float(info[key])
    for key in SCORE_INFO:
        if key in info:
            row[key] = float(info[key])
    for key in EVENT_COLUMNS:
        if key in info or key not in OPTIONAL_EVENTS:
            row[key] = bool(info[key])
    for term, value in info["reward_terms"].items():
        row[f"r_{term}"] = float(value)
    row.update(reward=float(reward), terminated=bool(terminated), truncated=bool(truncated))
    row.update(extra)
    return row


def to_frame(rows: list[dict]) -> pd.DataFrame:
    df = pd.DataFrame(rows)
    if not df.empty:
        df = df.sort_values(["episode", "agent", "step"], kind="stable").reset_index(drop=True)
    return df


def save(df: pd.DataFrame, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    df.to_parquet(path, index=False)
    return path


def load(path: Path) -> pd.DataFrame:
    return pd.read_parquet(path)
