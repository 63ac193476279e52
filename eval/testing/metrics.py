"""Driving metrics (SPEC §4) as pure functions over the per-step records.

Per AC per episode, first the driving score (the headline, cosim/score.py; docs/task.md,
"Driving score"), then the paper's metrics:

| metric | definition |
|---|---|
| DS | driving score: RC x IP, 0..1 |
| RC | route completion: the furthest credited progress along the route over its length, 0..1 (1 at the goal) |
| success | the goal reached with no infraction (no collision event, no red light) |
| IP | infraction penalty: 0.60 per vehicle event, 0.50 per pedestrian, 0.65 per object, 0.70 per red light, multiplied |
| CV events, CO events, CP events | collision events (one per other actor; the same actor again within 5 s is the same event) with vehicles (NaN without another vehicle), objects, pedestrians (NaN without one) |
| CV | fraction of steps in collision with another vehicle; NaN ("-") when no other vehicle existed |
| CO | fraction of steps in collision with a static road object |
| CP | fraction of steps in collision with a pedestrian; NaN ("-") when no pedestrian existed |
| OS | fraction of steps off the road or outside the lanes of its own direction |
| RL | fraction of steps on which it crossed a stop line against a red signal (beyond the paper) |
| TTFC | simulated seconds until the first collision of any kind; NaN ("--") when none |
| SPEED | mean forward speed, km/h |
| DISTANCE | abs(goal - spawn) - abs(goal - final position), metres (Euclidean) |

The driving score needs the records' columns ``event_vehicle``, ``event_pedestrian``,
``event_object`` and ``route_completion`` (records written since task version 4). Records
without them (older ones) give NaN for DS, RC, IP, success and the event counts (shown "-")
and a :class:`ScoreColumnsMissing` warning naming the missing columns; every other metric is
computed as before.

Success rates (RQ2, :func:`success_rates`, metrics.csv): Safety = 1 - the mean of CV, CO,
CP (those that apply); Efficiency = SPEED and DISTANCE; Lane keeping = 1 - OS. (The report's
figures count Safety per episode instead: the share of collision-free episodes,
eval/reporting/report.py ``per_episode``.)
"""

from __future__ import annotations

import functools
import warnings

import numpy as np
import pandas as pd

from cosim.score import episode_score

SCORE_METRICS = ("DS", "RC", "success", "IP", "CV_events", "CO_events", "CP_events")
"""The driving score's metrics (cosim/score.py), the report's first rows."""
PAPER_METRICS = ("CV", "CO", "CP", "OS", "RL", "TTFC", "SPEED", "DISTANCE")
"""The paper's metrics (SPEC §4)."""
METRICS = (*SCORE_METRICS, *PAPER_METRICS)
SCORE_COLUMNS = ("event_vehicle", "event_pedestrian", "event_object", "route_completion")
"""The per-step record columns the driving score is computed from."""
DEFINITIONS = {
    "DS": "driving score: route completion x infraction penalty (RC x IP), 0..1, per AC-episode "
          "(docs/task.md, \"Driving score\")",
    "RC": "route completion: the furthest progress credited along the route's lanes over the "
          "route's length, 0..1 (1 when the goal is reached)",
    "success": "share of AC-episodes that reached the goal with no infraction (no collision event, "
               "no red light)",
    "IP": "infraction penalty: the product of 0.60 per vehicle collision event, 0.50 per "
          "pedestrian, 0.65 per static object, 0.70 per red light crossed (CARLA Leaderboard)",
    "CV_events": "collision events with vehicles per AC-episode (one per other vehicle; the same "
                 "one again within 5 s is the same event)",
    "CO_events": "collision events with static road objects per AC-episode",
    "CP_events": "collision events with pedestrians per AC-episode",
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


class ScoreColumnsMissing(UserWarning):
    """Records without the driving score's columns (written before task version 4)."""


def missing_score_columns(records: pd.DataFrame) -> list[str]:
    """The :data:`SCORE_COLUMNS` ``records`` lack (absent, or NaN throughout)."""
    return [c for c in SCORE_COLUMNS if c not in records or records[c].isna().all()]


def score_of(episode: pd.DataFrame) -> dict:
    """DS, RC, IP, success and the collision event counts of one AC-episode's records (sorted
    by step); NaN for each where the records lack :data:`SCORE_COLUMNS`.

    RC is the largest running ``route_completion`` (1.0 once the goal is reached), the events
    are the steps on which a new event starts, red lights the steps that crossed one."""
    nan = dict.fromkeys(SCORE_METRICS, np.nan)
    if missing_score_columns(episode):
        return nan
    ev = {k: int(episode[f"event_{k}"].eq(True).sum())
          for k in ("vehicle", "pedestrian", "object")}
    red = int(episode["red_light"].astype(bool).sum()) if "red_light" in episode else 0
    goal = bool(episode["goal_reached"].any())
    score = episode_score(float(episode["route_completion"].max()), goal, ev["vehicle"],
                          ev["pedestrian"], ev["object"], red)
    others = "n_vehicles" not in episode or bool((episode["n_vehicles"] > 0).any())
    peds = "n_pedestrians" not in episode or bool((episode["n_pedestrians"] > 0).any())
    return {**score,
            "CV_events": float(ev["vehicle"]) if others else np.nan,
            "CO_events": float(ev["object"]),
            "CP_events": float(ev["pedestrian"]) if peds else np.nan}


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
    """One row per (episode, agent) with the driving score and the SPEC §4 metrics, return and
    length; ``dt``: the seconds per step of the environment the records are from
    (:func:`scenario_dt`). Records without :data:`SCORE_COLUMNS`: the score's metrics are NaN,
    with a :class:`ScoreColumnsMissing` warning."""
    if records.empty:
        return pd.DataFrame(columns=[*KEYS, *METRICS, "return", "steps", "goal"])
    missing = missing_score_columns(records)
    if missing:
        warnings.warn(f"the records have no {', '.join(missing)} column (recorded before the driving "
                      "score, task version 4): DS, RC, IP, success and the collision event counts are "
                      "NaN ('-')", ScoreColumnsMissing, stacklevel=2)
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
            **score_of(g),
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

