"""The degenerate-policy suite: does a scenario measure driving? (`cosim check-scenarios`)

A benchmark is only as good as what a trivial policy scores on it. This module
drives fixed reference policies through a scenario on held-out seeds, with the
test protocol's rules (collisions do not end an episode), and checks the validity
criteria of docs/scenarios.md:

- the ``autopilot`` (the scripted, privileged reference driver) and the
  ``autopilot-discrete`` (the same driver restricted to Discrete(9), the ceiling of a
  discrete learner) each reach at least ``AUTOPILOT_MIN_GOAL`` of the goals without a
  single vehicle, object or pedestrian collision;
- the ``safe-non-turner`` (the autopilot that holds before its route's first turn) never
  collides; it reaches the goals of the straight routes only, a row for learners to beat
  (docs/task.md, "Reference policies");
- every degenerate policy reaches at most ``DEGENERATE_MAX_GOAL`` of the goals and
  earns at most ``DEGENERATE_MAX_RETURN`` of the (continuous) autopilot's mean return.

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
DEGENERATE_MAX_GOAL = 0.2
DEGENERATE_MAX_RETURN = 0.5  # fraction of the autopilot's mean return
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
COLUMNS = ("return", "goal", "DISTANCE", "CV", "CO", "CP", "OS", "RL")


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
    """One row per (episode, AC): return, goal, DISTANCE, the step fractions CV..RL, TTFC
    (s to the first collision, NaN without one) and SPEED (mean forward speed, km/h);
    ``hold`` > 1 holds each of the policy's actions for that many steps (:func:`held`)."""
    sc = TestConditions.of(1, steps).scenario(scenario)
    rows = []
    with World(sc, num_agents) as world:
        for ep in range(episodes):
            ep_seed = seed + ep
            rng = np.random.default_rng(ep_seed)
            first = world.reset(seed=ep_seed)
            act = held(_controller(policy, world, rng), int(hold))
            acc = {ac: dict.fromkeys(("return", "n", "cv", "co", "cp", "os", "rl", "goal", "speed"),
                                     0.0) | {"ttfc": np.nan}
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
                })
    return pd.DataFrame(rows)


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
    extra = [c for c in ("TTFC", "SPEED") if c in rows.columns]
    table = rows.groupby("policy", sort=False)[[*COLUMNS, "collision_steps", *extra]].mean()
    table["n"] = rows.groupby("policy", sort=False).size()
    return table.reindex([p for p in POLICIES if p in table.index])


def failures(table: pd.DataFrame) -> list[str]:
    """The validity criteria that a summary table breaks (empty: the scenario is valid)."""
    out = []
    if "autopilot" not in table.index:
        return ["the autopilot was not run, so no criterion can be checked"]
    ap = table.loc["autopilot"]
    for name in DRIVERS:
        if name not in table.index:
            continue
        row = table.loc[name]
        if row["goal"] < AUTOPILOT_MIN_GOAL:
            out.append(f"{name} reaches {row['goal']:.0%} of goals (needs >= {AUTOPILOT_MIN_GOAL:.0%})")
        if row["collision_steps"] > 0:
            out.append(f"{name} collides ({row['collision_steps']:.2f} collision steps per AC)")
    if "safe-non-turner" in table.index and table.loc["safe-non-turner", "collision_steps"] > 0:
        steps = table.loc["safe-non-turner", "collision_steps"]
        out.append(f"safe-non-turner collides ({steps:.2f} collision steps per AC)")
    limit = DEGENERATE_MAX_RETURN * ap["return"]
    for name in table.index:
        if name in REFERENCES:
            continue
        row = table.loc[name]
        if row["goal"] > DEGENERATE_MAX_GOAL:
            out.append(f"{name} reaches {row['goal']:.0%} of goals (allowed <= {DEGENERATE_MAX_GOAL:.0%})")
        if row["return"] > limit:
            out.append(f"{name} earns {row['return']:.0f}, more than {DEGENERATE_MAX_RETURN:.0%} "
                       f"of the autopilot's {ap['return']:.0f}")
    return out


def format_table(table: pd.DataFrame) -> str:
    """The summary as a Markdown table (CV and CP "-" where no vehicle / pedestrian existed)."""
    head = "| policy | return | goal rate | DISTANCE m | CV | CO | CP | OS | RL |"
    lines = [head, "|" + "---|" * 9]
    for name, r in table.iterrows():
        cells = [f"{r['return']:.0f}", f"{r['goal']:.2f}", f"{r['DISTANCE']:.1f}"]
        cells += ["-" if pd.isna(r[c]) else f"{r[c]:.3f}" for c in ("CV", "CO", "CP", "OS", "RL")]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
