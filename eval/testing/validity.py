"""The degenerate-policy suite: does a scenario measure driving? (`cosim check-scenarios`)

A benchmark is only as good as what a trivial policy scores on it. This module
drives fixed reference policies through a scenario on held-out seeds, with the
test protocol's rules (collisions do not end an episode), and checks the validity
criteria of docs/scenarios.md:

- the ``autopilot`` (the scripted, privileged reference driver) and the
  ``autopilot-discrete`` (the same driver restricted to Discrete(9), the ceiling of a
  discrete learner) each reach a mean driving score of at least ``AUTOPILOT_MIN_DS`` and at
  least ``AUTOPILOT_MIN_GOAL`` of the goals without a single vehicle, object or pedestrian
  collision;
- the ``safe-non-turner`` (the autopilot that holds before its route's first turn) never
  collides; it reaches the goals of the straight routes only, and its driving score is a row
  for learners to beat (docs/task.md, "Reference policies");
- every degenerate policy reaches at most ``DEGENERATE_MAX_GOAL`` of the goals, and every one
  but ``always-coast`` a mean driving score of at most ``DEGENERATE_MAX_DS``. The ACs enter
  moving (7-8 m/s, SPEC's validity) on routes of 75-235 m, so a car that never touches a pedal
  rolls 8-32% of its route in its lane before it stops: ``always-coast``'s DS is that entry roll
  (``ROLL_POLICY``), reported in the table and cleared by the verdict like every degenerate row,
  not held to ``DEGENERATE_MAX_DS`` (docs/scenarios.md, "Validity").

The driving score (cosim/score.py; docs/task.md, "Driving score") replaced the earlier
criterion on the return (a degenerate policy earning at most half the autopilot's): the
return is still in the table.

The policies need no camera, so they run on :class:`cosim.world.World` (no
rendering): a whole environment takes seconds to a minute.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pandas as pd

from cosim.controller import Autopilot, NonTurner
from cosim.dynamics import discrete_controls
from cosim.scenario import Scenario, load_scenario
from cosim.world import World
from eval.testing.conditions import TestConditions

AUTOPILOT_MIN_GOAL = 0.9
AUTOPILOT_MIN_DS = 0.9  # mean driving score of each autopilot
DEGENERATE_MAX_GOAL = 0.2
DEGENERATE_MAX_DS = 0.1  # mean driving score of every degenerate policy but ROLL_POLICY
ROLL_POLICY = "always-coast"
"""The degenerate policy whose DS is the entry roll (above): held to the goal criterion only."""
HELD_OUT_SEED = 10_000  # episode seeds start here; training runs use small seeds

_TABLE = discrete_controls()  # the Discrete(9) table in World.step's units (cosim.dynamics)

# the scripted references (cosim/controller.py): they must drive (autopilots) or be safe
REFERENCES = ("autopilot", "autopilot-discrete", "safe-non-turner")
DRIVERS = ("autopilot", "autopilot-discrete")  # held to AUTOPILOT_MIN_GOAL with no collision
# name -> what it does, as (throttle(+)/brake(-), steer of max_steer) with steer < 0 = left;
# "random" and "random-box" draw a new action every step
DEGENERATE: dict[str, tuple[float, float] | None] = {
    "random": None,  # uniform over the nine discrete actions (SPEC's Discrete(9) table)
    "random-box": None,  # uniform over Box(-1, 1, (2,))
    "always-forward": (1.0, 0.0),
    "always-coast": (0.0, 0.0),
    "always-brake": (-1.0, 0.0),
    "full-left": (0.5, -1.0),
    "full-right": (0.5, 1.0),
    "forward-drift-left": tuple(_TABLE[5]),  # discrete action 5: forward with a small steer
    "forward-drift-right": tuple(_TABLE[6]),  # discrete action 6
}
_DRIFT = {"forward-drift-left": 5, "forward-drift-right": 6}  # their discrete actions
POLICIES = (*REFERENCES, *DEGENERATE)
SCORE_COLUMNS = ("DS", "RC", "success", "IP", "CV_events", "CO_events", "CP_events")
"""The driving score's columns (as eval.testing.metrics.SCORE_METRICS)."""
COLUMNS = (*SCORE_COLUMNS, "return", "goal", "DISTANCE", "CV", "CO", "CP", "OS", "RL")


def _controller(name: str, world: World, rng: np.random.Generator) -> Callable[[str], tuple]:
    table = discrete_controls(world.vehicle)  # the scenario's car (a `vehicle:` block may change it)
    if name == "autopilot":
        pilots = {ac: Autopilot(world, ac) for ac in world.ac_ids}
        return lambda ac: tuple(pilots[ac].act())
    if name == "autopilot-discrete":
        pilots = {ac: Autopilot(world, ac) for ac in world.ac_ids}
        return lambda ac: tuple(table[pilots[ac].act_discrete()])
    if name == "safe-non-turner":
        pilots = {ac: NonTurner(world, ac) for ac in world.ac_ids}
        return lambda ac: tuple(pilots[ac].act())
    if name == "random":
        return lambda ac: tuple(table[rng.integers(len(table))])
    if name == "random-box":
        return lambda ac: tuple(rng.uniform(-1.0, 1.0, 2))
    fixed = tuple(table[_DRIFT[name]]) if name in _DRIFT else DEGENERATE[name]
    return lambda ac: fixed


def held(act: Callable[[str], tuple], hold: int) -> Callable[[str], tuple]:
    """``act`` (AC id -> action) deciding at each AC's calls 0, ``hold``, 2 ``hold``, ... and
    repeating that action in between: a controller under an action repeat (docs/task.md,
    "Action repeat")."""
    if hold == 1:
        return act
    count: dict[str, int] = {}
    last: dict[str, tuple] = {}

    def repeat(ac: str) -> tuple:
        if count.get(ac, 0) % hold == 0:
            last[ac] = act(ac)
        count[ac] = count.get(ac, 0) + 1
        return last[ac]

    return repeat


def run_policy(scenario: Scenario, policy: str, num_agents: int, episodes: int,
               steps: int | None = None, seed: int = HELD_OUT_SEED, hold: int = 1) -> pd.DataFrame:
    """One row per (episode, AC): the driving score DS, route completion RC, success,
    infraction penalty IP and collision events per kind (cosim/score.py; CV_events NaN
    without another vehicle, CP_events without a pedestrian, as CV and CP), return, goal,
    DISTANCE, the step fractions CV..RL, TTFC (s to the first collision, NaN without one) and
    SPEED (mean forward speed, km/h);
    ``hold`` > 1 holds each of the policy's actions for that many steps (:func:`held`)."""
    sc = TestConditions.of(1, steps).scenario(scenario)
    rows = []
    with World(sc, num_agents) as world:
        for ep in range(episodes):
            ep_seed = seed + ep
            rng = np.random.default_rng(ep_seed)
            first = world.reset(seed=ep_seed)
            act = held(_controller(policy, world, rng), int(hold))
            acc = {ac: dict.fromkeys(("return", "n", "cv", "co", "cp", "os", "rl", "goal", "speed",
                                      "ev", "eo", "ep", "rc"), 0.0) | {"ttfc": np.nan}
                   for ac in world.ac_ids}
            last = {ac: (r.x, r.y) for ac, r in first.items()}
            saw = {"vehicles": False, "persons": False}
            while world.active:
                results = world.step({ac: act(ac) for ac in world.active})
                snap = world.snapshot
                saw["vehicles"] |= len(snap.vehicle_ids) > len(world.active)
                saw["persons"] |= len(snap.person_ids) > 0
                for ac, r in results.items():
                    a, ev = acc[ac], r.events
                    a["return"] += r.reward
                    a["n"] += 1
                    a["cv"] += ev.collision_vehicle
                    a["co"] += ev.collision_object
                    a["cp"] += ev.collision_pedestrian
                    a["os"] += ev.lane_violation
                    a["rl"] += ev.red_light
                    a["ev"] += ev.event_vehicle
                    a["eo"] += ev.event_object
                    a["ep"] += ev.event_pedestrian
                    a["rc"] = max(a["rc"], float(ev.route_completion))
                    a["goal"] = max(a["goal"], float(ev.goal_reached))
                    a["speed"] += ev.speed
                    if ev.collision and np.isnan(a["ttfc"]):
                        a["ttfc"] = a["n"] * sc.dt  # as eval.testing.metrics: seconds to the first hit
                    last[ac] = (r.x, r.y)
            for i, ac in enumerate(world.ac_ids):
                a, route = acc[ac], world.routes[i]
                n = max(a["n"], 1.0)
                gx, gy = route.goal_point
                sx, sy = route.spawn_xy
                fx, fy = last[ac]
                rows.append({
                    "policy": policy, "episode": ep, "seed": ep_seed, "agent": ac,
                    "return": a["return"], "goal": a["goal"],
                    "DISTANCE": float(np.hypot(gx - sx, gy - sy) - np.hypot(gx - fx, gy - fy)),
                    "CV": a["cv"] / n if saw["vehicles"] else np.nan,
                    "CO": a["co"] / n,
                    "CP": a["cp"] / n if saw["persons"] else np.nan,
                    "OS": a["os"] / n, "RL": a["rl"] / n,
                    "TTFC": a["ttfc"], "SPEED": 3.6 * a["speed"] / n,
                    "collision_steps": a["cv"] + a["co"] + a["cp"],
                    **score_row(a, saw),
                })
    return pd.DataFrame(rows)


def score_row(a: dict, saw: dict) -> dict:
    """DS, RC, success, IP and the event counts of one AC-episode from :func:`run_policy`'s
    sums (``ev``/``eo``/``ep``: collision events, ``rl``: red lights, ``rc``: the largest
    running route completion, ``goal``)."""
    from cosim.score import episode_score

    score = episode_score(a["rc"], bool(a["goal"]), int(a["ev"]), int(a["ep"]), int(a["eo"]), int(a["rl"]))
    return {**score, "CV_events": a["ev"] if saw["vehicles"] else np.nan, "CO_events": a["eo"],
            "CP_events": a["ep"] if saw["persons"] else np.nan,
            "collision_events": a["ev"] + a["eo"] + a["ep"]}


def check_scenario(scenario: Scenario | str, num_agents: int, episodes: int,
                   steps: int | None = None, policies=POLICIES,
                   progress: Callable[[str], None] | None = None) -> pd.DataFrame:
    """Every policy's per-(episode, AC) rows for one scenario and AC count."""
    sc = load_scenario(scenario) if isinstance(scenario, str) else scenario
    frames = []
    for policy in policies:
        if progress:
            progress(policy)
        frames.append(run_policy(sc, policy, num_agents, episodes, steps))
    return pd.concat(frames, ignore_index=True)


def summarize(rows: pd.DataFrame) -> pd.DataFrame:
    """Mean per policy (in POLICIES order) of every column, plus collision steps (and TTFC, the
    mean over the AC-episodes with a collision, and SPEED, when the rows have them: the report's
    reference columns)."""
    extra = [c for c in ("TTFC", "SPEED", "collision_events") if c in rows.columns]
    cols = [c for c in COLUMNS if c in rows.columns]  # rows from before the driving score lack DS..
    table = rows.groupby("policy", sort=False)[[*cols, "collision_steps", *extra]].mean()
    table["n"] = rows.groupby("policy", sort=False).size()
    return table.reindex([p for p in POLICIES if p in table.index])


def failures(table: pd.DataFrame) -> list[str]:
    """The validity criteria that a summary table breaks (empty: the scenario is valid); a
    table without a driving score (``DS`` missing or NaN) fails its DS criteria as not measured."""
    out = []
    if "autopilot" not in table.index:
        return ["the autopilot was not run, so no criterion can be checked"]

    def ds(name: str) -> float:
        return float(table.loc[name, "DS"]) if "DS" in table.columns else float("nan")

    for name in DRIVERS:
        if name not in table.index:
            continue
        row = table.loc[name]
        if not np.isfinite(ds(name)):
            out.append(f"{name}: no driving score measured (needs >= {AUTOPILOT_MIN_DS:.2f})")
        elif ds(name) < AUTOPILOT_MIN_DS:
            out.append(f"{name} scores DS {ds(name):.3f} (needs >= {AUTOPILOT_MIN_DS:.2f})")
        if row["goal"] < AUTOPILOT_MIN_GOAL:
            out.append(f"{name} reaches {row['goal']:.0%} of goals (needs >= {AUTOPILOT_MIN_GOAL:.0%})")
        if row["collision_steps"] > 0:
            out.append(f"{name} collides ({row['collision_steps']:.2f} collision steps per AC)")
    if "safe-non-turner" in table.index and table.loc["safe-non-turner", "collision_steps"] > 0:
        steps = table.loc["safe-non-turner", "collision_steps"]
        out.append(f"safe-non-turner collides ({steps:.2f} collision steps per AC)")
    for name in table.index:
        if name in REFERENCES:
            continue
        row = table.loc[name]
        if not np.isfinite(ds(name)):
            out.append(f"{name}: no driving score measured (allowed <= {DEGENERATE_MAX_DS:.2f})")
        elif ds(name) > DEGENERATE_MAX_DS and name != ROLL_POLICY:
            out.append(f"{name} scores DS {ds(name):.3f} (allowed <= {DEGENERATE_MAX_DS:.2f})")
        if row["goal"] > DEGENERATE_MAX_GOAL:
            out.append(f"{name} reaches {row['goal']:.0%} of goals (allowed <= {DEGENERATE_MAX_GOAL:.0%})")
    return out


def score_line(table: pd.DataFrame) -> str:
    """Each reference's driving score in one line, and the strongest degenerate policy's:
    what `cosim check-scenarios` prints under each table."""
    if "DS" not in table.columns:
        return "driving score: not measured (rows without DS)"

    def v(name):
        x = float(table.loc[name, "DS"])
        return f"{x:.3f}" if np.isfinite(x) else "-"

    parts = [f"{p} {v(p)}" for p in REFERENCES if p in table.index]
    degenerate = table.loc[[p for p in table.index if p not in REFERENCES and p != ROLL_POLICY],
                           "DS"].astype(float)
    if degenerate.notna().any():
        best = degenerate.idxmax()
        parts.append(f"best degenerate {best} {v(best)}")
    if ROLL_POLICY in table.index:
        parts.append(f"{ROLL_POLICY} (the entry roll) {v(ROLL_POLICY)}")
    return (f"driving score (DS; autopilots need >= {AUTOPILOT_MIN_DS:.2f}, degenerate policies "
            f"but {ROLL_POLICY} <= {DEGENERATE_MAX_DS:.2f}): " + ", ".join(parts))


def format_table(table: pd.DataFrame) -> str:
    """The summary as a Markdown table: the driving score DS, route completion RC and success
    rate first, then the return, goal rate, DISTANCE, the step fractions CV..RL and the
    collision events per AC-episode (vehicle / object / pedestrian). "-": does not apply (CV
    and CP where no vehicle / pedestrian existed) or not measured (no DS in the rows)."""
    head = ("| policy | DS | RC | success | return | goal rate | DISTANCE m | CV | CO | CP | OS | RL "
            "| events V / O / P |")
    lines = [head, "|" + "---|" * 13]

    def num(r, c, d):
        return "-" if c not in r.index or pd.isna(r[c]) else f"{r[c]:.{d}f}"

    for name, r in table.iterrows():
        cells = [num(r, "DS", 3), num(r, "RC", 3), num(r, "success", 2),
                 f"{r['return']:.0f}", f"{r['goal']:.2f}", f"{r['DISTANCE']:.1f}"]
        cells += [num(r, c, 3) for c in ("CV", "CO", "CP", "OS", "RL")]
        cells.append(" / ".join(num(r, c, 2) for c in ("CV_events", "CO_events", "CP_events")))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
