"""The default collision rule leaves no crash exit (docs/task.md, "Collision rule").

Computed from the bundled scenarios' real reward weights (cosim.scenario.RewardWeights as
the YAML sets them, the terms of cosim.events.REWARD_TERMS), their horizon, their collision
event window and the learning car's top speed, discounted with gamma 0.99: for every step t of
the episode, an AC that crashes at t under the default (once per event, what it drives into
stops it: then it pushes against it to the horizon, or stands) earns less than one that brakes
and waits from t; under the paper's rule (a collision ends the episode) crashing wins whenever
enough steps remain. tests/cosim/test_collision_rule.py checks in the simulator the premise
that a blocked crash step earns no efficiency and leaves the car standing where it was.
"""

from __future__ import annotations

import numpy as np
import pytest

GAMMA = 0.99


def exits(weights, horizon: int, dt: float, speed_limit: float, max_speed: float,
          gamma: float = GAMMA, window_steps: int = 50) -> dict[str, np.ndarray]:
    """Discounted return from step t (index t = 0..horizon-1) of each way to spend the rest of
    an episode, from a standing car on its own lane at step t.

    ``wait``: brake and stand to the horizon (only the step constant). The default rule (once
    per event, blocked): ``crash_push``: collide at t and push against it to the horizon, a
    charge every ``window_steps``; ``crash_stand``: collide at t, then stand. The per-step rule
    without solid cars (task version 3): ``crash_stay``: collide at t and stay in contact every
    step to the horizon; ``crash_leave``: collide at t, then stand out of contact.
    ``crash_end``: the paper's rule, the collision ends the episode. The per-step and paper's
    crash steps are credited the most efficiency a step can earn (the top speed's progress plus
    F = 1), so a crash is never undersold; a blocked step earns none (cosim/world.py).
    """
    from cosim.events import REWARD_TERMS

    assert set(REWARD_TERMS) == {"collision", "efficiency", "lane", "step", "red_light"}, (
        "a new reward term: add it to this calculation and to docs/task.md, Collision rule")
    c, s = weights.collision, weights.step
    best_eff = weights.efficiency * (max_speed * dt + 1.0)  # progress <= v_max dt, F <= 1
    n = horizon - np.arange(horizon)  # steps left, this one included
    disc = lambda k: (1 - gamma ** k) / (1 - gamma)  # noqa: E731 - sum of gamma^0..gamma^(k-1)
    wait = s * disc(n)
    charges = np.array([sum(gamma ** (window_steps * j) for j in range(-(-k // window_steps))) for k in n])
    return {
        "wait": wait,
        "crash_push": wait + c * charges,
        "crash_stand": wait + c,
        "crash_stay": (c + s + best_eff) * disc(n),
        "crash_leave": c + s + best_eff + gamma * s * disc(n - 1),
        "crash_end": np.full(horizon, c + s + best_eff),
        "crash_end_no_eff": np.full(horizon, c + s),
    }


def _cases():
    from cosim.scenario import available_scenarios, load_scenario
    from eval.training.presets import load_presets

    horizons = {p.horizon for p in load_presets().values()}
    for name in available_scenarios():
        sc = load_scenario(name)
        for h in sorted(horizons | {sc.horizon}):
            yield pytest.param(name, h, id=f"{name}-h{h}")


@pytest.mark.parametrize(("name", "horizon"), list(_cases()))
def test_no_crash_exit_beats_braking_and_waiting_at_any_step(name, horizon):
    from cosim.dynamics import VehicleParams
    from cosim.scenario import load_scenario

    sc = load_scenario(name)
    # the default rule: a collision does not end the episode, one charge per event, solid cars
    assert sc.termination.on_collision is False
    assert sc.contact.charge == "event" and sc.solid_cars
    window = round(sc.contact.window / sc.dt)
    v = exits(sc.reward, horizon, sc.dt, sc.speed_limit, VehicleParams().max_speed, window_steps=window)
    for kind in ("crash_push", "crash_stand", "crash_stay", "crash_leave"):
        worse = v[kind] < v["wait"]
        assert worse.all(), (f"{name}, horizon {horizon}: {kind} beats waiting at t = "
                             f"{np.flatnonzero(~worse).tolist()[:5]}")
    # the paper's rule: crashing out is worth more than waiting exactly where the wait's
    # discounted step costs exceed one collision
    left = horizon - np.arange(horizon)
    assert ((v["crash_end_no_eff"] > v["wait"])
            == (-sc.reward.step * (1 - GAMMA ** left) / (1 - GAMMA) > -sc.reward.collision - sc.reward.step)).all()


def test_the_table_in_docs_task_md():
    """The H = 600 table of docs/task.md, "Collision rule", row by row."""
    from cosim.scenario import load_scenario

    sc = load_scenario("env_3")
    v = exits(sc.reward, 600, sc.dt, sc.speed_limit, 25.0)
    rows = {0: (-99.8, -226.0, -149.8, -51.0, -16.0), 500: (-63.4, -143.6, -113.4, -51.0, -16.0),
            530: (-50.5, -130.8, -100.5, -51.0, -16.0), 590: (-9.6, -59.6, -59.6, -51.0, -16.0),
            599: (-1.0, -51.0, -51.0, -51.0, -16.0)}
    for t, row in rows.items():
        got = tuple(round(float(v[k][t]), 1) for k in
                    ("wait", "crash_push", "crash_stand", "crash_end_no_eff", "crash_end"))
        assert got == row, (t, got)


def test_the_paper_rule_pays_for_crashing_with_71_or_more_steps_left():
    """The number quoted in docs/task.md: with the bundled weights (-50, -1) and gamma 0.99
    a crash that ends the episode beats waiting whenever 71 or more steps remain (18 if the
    crash step itself is credited a full-speed step's efficiency)."""
    from cosim.scenario import load_scenario

    sc = load_scenario("env_3")
    v = exits(sc.reward, 600, sc.dt, sc.speed_limit, 25.0)
    left = 600 - np.arange(600)
    assert left[v["crash_end_no_eff"] > v["wait"]].min() == 71
    assert left[v["crash_end"] > v["wait"]].min() == 18


def test_training_defaults_to_the_test_rule_and_the_paper_rule_is_one_flag_away():
    from eval.cli import build_parser
    from eval.training.config import make_config

    assert make_config("ppo", "env_1", "smoke").collisions_end_episode is False
    assert make_config("ppo", "env_1", "smoke", collisions="end").collisions_end_episode is True
    parser = build_parser()
    assert parser.parse_args(["train"]).collisions == "event"
    assert make_config("ppo", "env_1", "smoke").collision_charge == "event"
    assert make_config("ppo", "env_1", "smoke", collisions="step").collision_charge == "step"
    assert parser.parse_args(["train", "--collisions", "end"]).collisions == "end"
