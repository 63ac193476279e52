"""Driving metrics (SPEC §4) as pure functions over the per-step records.

Per AC per episode:

| metric | definition |
|---|---|
| CV | fraction of steps in collision with another vehicle; NaN ("-") when no other vehicle existed |
| CO | fraction of steps in collision with a static road object |
| CP | fraction of steps in collision with a pedestrian; NaN ("-") when no pedestrian existed |
| OS | fraction of steps off the road or outside the lanes of its own direction |
| RL | fraction of steps on which it crossed a stop line against a red signal (beyond the paper) |
| TTFC | simulated seconds until the first collision of any kind; NaN ("--") when none |
| SPEED | mean forward speed, km/h |
| DISTANCE | abs(goal - spawn) - abs(goal - final position), metres (Euclidean) |

Success rates (RQ2, :func:`success_rates`, metrics.csv): Safety = 1 - the mean of CV, CO,
CP (those that apply); Efficiency = SPEED and DISTANCE; Lane keeping = 1 - OS. (The report's
figures count Safety per episode instead: the share of collision-free episodes,
eval/reporting/report.py ``per_episode``.)
"""

from __future__ import annotations

import functools

import numpy as np
import pandas as pd

METRICS = ("CV", "CO", "CP", "OS", "RL", "TTFC", "SPEED", "DISTANCE")
DEFINITIONS = {
    "CV": "collision with another vehicle: fraction of the AC's steps in contact with one",
    "CO": "collision with a static road object: fraction of steps",
    "CP": "collision with a pedestrian: fraction of steps",
    "OS": "off its side: fraction of steps off the road or outside the lanes of its own direction",
    "RL": "red light: fraction of steps on which it crossed a stop line against a red signal",
    "TTFC": "time to first collision of any kind, simulated seconds",
    "SPEED": "mean forward speed, km/h",
    "DISTANCE": "progress towards the goal: abs(goal - spawn) - abs(goal - final position), metres",
    "return": "undiscounted sum of the AC's rewards over the episode",
    "goal": "share of episodes in which the AC reached its goal",
}
"""Each metric's definition in words (the table above): the legend of every report."""
KEYS = ["episode", "agent", "algorithm"]


@functools.cache
def scenario_dt(env: str) -> float:
    """Seconds per step of the environment ``env`` (a scenario name or YAML path): its
    scenario's ``dt``, what turns the records' step counts into seconds (TTFC, time axes)."""
    from cosim.scenario import load_scenario

    return float(load_scenario(env).dt)


def distance_driven(episode: pd.DataFrame) -> float:
    """DISTANCE of one AC-episode's records (sorted by step): how much nearer its goal it
    ended than it started, metres, straight-line."""
    last = episode.iloc[-1]
    spawn_to_goal = float(np.hypot(last.goal_x - last.spawn_x, last.goal_y - last.spawn_y))
    return spawn_to_goal - float(np.hypot(last.goal_x - last.x, last.goal_y - last.y))


def episode_metrics(records: pd.DataFrame, dt: float) -> pd.DataFrame:
    """One row per (episode, agent) with the SPEC §4 metrics, return and length; ``dt``: the
    seconds per step of the environment the records are from (:func:`scenario_dt`)."""
    if records.empty:
        return pd.DataFrame(columns=[*KEYS, *METRICS, "return", "steps"])
    rows = []
    for (episode, agent, algorithm), g in records.groupby(KEYS, sort=True):
        g = g.sort_values("step")
        n = len(g)
        others = bool((g["n_vehicles"] > 0).any())
        peds = bool((g["n_pedestrians"] > 0).any())
        hits = np.flatnonzero(g["collision"].to_numpy())
        rows.append({
            "episode": episode,
            "agent": agent,
            "algorithm": algorithm,
            "CV": g["collision_vehicle"].mean() if others else np.nan,
            "CO": g["collision_object"].mean(),
            "CP": g["collision_pedestrian"].mean() if peds else np.nan,
            "OS": g["lane_violation"].mean(),
            "RL": g["red_light"].mean() if "red_light" in g else 0.0,
            "TTFC": (hits[0] + 1) * dt if len(hits) else np.nan,
            "SPEED": g["speed"].mean() * 3.6,
            "DISTANCE": distance_driven(g),
            "return": g["reward"].sum(),
            "steps": n,
            "goal": bool(g["goal_reached"].any()),
        })
    return pd.DataFrame(rows)


def summarize(per_episode: pd.DataFrame, by: list[str] | None = None) -> pd.DataFrame:
    """Means over episodes (NaN-aware: a '-' metric stays '-' only if it never applied)."""
    by = by or ["algorithm"]
    cols = [*METRICS, "return", "steps", "goal"]
    return per_episode.groupby(by)[cols].mean(numeric_only=False).reset_index()


def success_rates(summary: pd.DataFrame) -> pd.DataFrame:
    """RQ2: Safety (1 - mean of CV, CO, CP that apply), Efficiency inputs, Lane keeping (1 - OS)."""
    out = summary.copy()
    out["safety"] = 1.0 - summary[["CV", "CO", "CP"]].mean(axis=1, skipna=True)
    out["lane_keeping"] = 1.0 - summary["OS"]
    return out


def speed_curve(records: pd.DataFrame, by: list[str] | None = None) -> pd.DataFrame:
    """Mean speed (km/h) per timestep, for the SPEED-per-timestep figure."""
    by = by or ["algorithm"]
    return (records.assign(speed_kmh=records["speed"] * 3.6)
            .groupby([*by, "step"])["speed_kmh"].mean().reset_index())
