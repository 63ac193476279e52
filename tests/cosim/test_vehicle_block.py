"""A scenario's ``vehicle:`` block (cosim/scenario.py): VehicleParams by field name, angles in
degrees, ``max_lateral_accel: null`` for no grip limit. It is how the steering before issue 25
(discrete fractions of 35 degrees, no grip limit) is run; the defaults stay as they are."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from cosim.dynamics import (
    DISCRETE_ACTIONS,
    VehicleParams,
    action_to_control,
    bicycle_step,
    discrete_controls,
)
from cosim.errors import ScenarioError
from cosim.scenario import load_scenario, scenario_data

ENVS = ["env_1", "env_2", "env_3", "env_4", "env_5"]
OLD = {"discrete_steer_reference": 35, "max_lateral_accel": None}
# action -> wheel angle in degrees (positive = left), before issue 25: fractions of 35 degrees
OLD_ANGLES = {0: 0.0, 1: 17.5, 2: -17.5, 3: 0.0, 4: 0.0, 5: 1.75, 6: -1.75, 7: 17.5, 8: -17.5}
NEW_ANGLES = {0: 0.0, 1: 35.0, 2: -35.0, 3: 0.0, 4: 0.0, 5: 3.5, 6: -3.5, 7: 35.0, 8: -35.0}


def _old_bicycle_step(x, y, heading, speed, throttle_brake, steer, params, dt):
    """cosim.dynamics.bicycle_step as it was before issue 25 (1ecabdc^): no grip limit."""
    accel = np.where(throttle_brake >= 0, throttle_brake * params.max_accel,
                     throttle_brake * params.max_brake)
    resist = np.where(speed > 0, params.rolling_decel + params.drag * speed * speed, 0.0)
    new_speed = np.clip(speed + (accel - resist) * dt, 0.0, params.max_speed)
    v = 0.5 * (speed + new_speed)
    delta = -steer * params.max_steer
    beta = np.arctan(0.5 * np.tan(delta))
    new_heading = heading + v / params.wheelbase * np.cos(beta) * np.tan(delta) * dt
    mid = 0.5 * (heading + new_heading)
    new_x = x + v * np.cos(mid + beta) * dt
    new_y = y + v * np.sin(mid + beta) * dt
    new_heading = (new_heading + np.pi) % (2 * np.pi) - np.pi
    return new_x, new_y, new_heading, new_speed


def _scenario_yaml(folder: Path, name="env_4", vehicle=None, relative=True) -> Path:
    """A copy of a bundled scenario in ``folder`` whose file paths are relative to the copy
    (as a user's own scenario would have them), with a ``vehicle:`` block."""
    data = scenario_data(name, relative_to=folder if relative else None)
    if vehicle is not None:
        data["vehicle"] = vehicle
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / f"{name}_vehicle.yaml"
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


@pytest.mark.parametrize("env", ENVS)
def test_the_default_car_is_unchanged(env):
    sc = load_scenario(env)
    assert sc.vehicle == VehicleParams() and hash(sc.vehicle) == hash(VehicleParams())
    p = sc.vehicle
    assert math.degrees(p.max_steer) == pytest.approx(35.0)
    assert math.degrees(p.discrete_steer_reference) == pytest.approx(70.0)
    assert p.max_lateral_accel == 8.0
    assert np.array_equal(discrete_controls(p), discrete_controls())
    for action, degrees in NEW_ANGLES.items():
        steer = action_to_control(action, True, "ac_0", p)[1]
        assert math.degrees(p.wheel_angle(steer, 3.0)) == pytest.approx(degrees)


def test_the_old_block_gives_the_old_wheel_angles_at_every_speed(tmp_path):
    for grip_off in (None, "off"):
        sc = load_scenario(_scenario_yaml(tmp_path, vehicle={**OLD, "max_lateral_accel": grip_off}))
        p = sc.vehicle
        assert p.max_lateral_accel == math.inf
        assert p.discrete_steer_reference == p.max_steer == VehicleParams().max_steer
        # the table in the bicycle's units is the paper's numbers as they are (fractions of 35)
        assert np.array_equal(discrete_controls(p), DISCRETE_ACTIONS)
        for action, degrees in OLD_ANGLES.items():
            steer = action_to_control(action, True, "ac_0", p)[1]
            assert steer == DISCRETE_ACTIONS[action, 1]
            for speed in (0.0, 3.0, 10.0, 25.0):  # no grip limit: the same angle at any speed
                assert math.degrees(p.wheel_angle(steer, speed)) == pytest.approx(degrees)
        # and the bicycle moves exactly as it did before issue 25, for every action and speed
        rng = np.random.default_rng(0)
        n = 500
        state = [rng.uniform(-50, 50, n), rng.uniform(-50, 50, n), rng.uniform(-3, 3, n),
                 rng.uniform(0, 25, n)]
        table = discrete_controls(p)
        actions = rng.integers(0, 9, n)
        tb, steer = table[actions, 0], table[actions, 1]
        new = bicycle_step(*state, tb, steer, p, 0.1)
        old = _old_bicycle_step(*state, DISCRETE_ACTIONS[actions, 0], DISCRETE_ACTIONS[actions, 1],
                                VehicleParams(), 0.1)
        for a, b in zip(new, old, strict=True):
            np.testing.assert_array_equal(a, b)


def test_an_env_on_the_old_block_steers_its_discrete_actions_with_the_old_wheel(tmp_path):
    """The env maps a discrete action with the scenario's car (not the default one): "left"
    from 7 m/s turns the car as the old bicycle did (17.5 degrees, no grip limit)."""
    from cosim.env import CosimParallelEnv

    path = _scenario_yaml(tmp_path, vehicle=OLD)
    env = CosimParallelEnv(path, num_agents=1, background=False, pedestrians=False)
    try:
        env.reset(seed=3)
        world = env.world
        assert world.vehicle == load_scenario(path).vehicle and env.mirror.vehicle == world.vehicle
        before = world.ac_state("ac_0")
        env.step({"ac_0": 1})  # left
        after = world.ac_state("ac_0")
    finally:
        env.close()
    old = _old_bicycle_step(*(np.array([v]) for v in before), np.array([0.0]), np.array([-0.5]),
                            VehicleParams(), 0.1)
    assert after == pytest.approx(tuple(float(v[0]) for v in old), abs=1e-9)
    # the new wheel would have turned it at the grip limit, more than the old 17.5 degrees here
    new = bicycle_step(*(np.array([v]) for v in before), np.array([0.0]), np.array([-1.0]),
                       VehicleParams(), 0.1)
    assert abs(float(new[2][0]) - before[2]) > abs(after[2] - before[2]) + 1e-3


def test_a_scenario_by_path_resolves_its_files_relative_to_the_yaml(tmp_path):
    path = _scenario_yaml(tmp_path / "study" / "scenarios", vehicle=OLD)
    data = yaml.safe_load(path.read_text())
    assert not any(Path(f).is_absolute() for f in [data["net"], *data["demand"]])  # relative
    sc = load_scenario(path)
    assert sc.demand == load_scenario("env_4").demand and all(f.exists() for f in sc.demand)
    assert sc.net == load_scenario("env_4").net and sc.source == path


@pytest.mark.parametrize("vehicle, message", [
    ({"max_steering": 35}, r"unknown key\(s\) \['max_steering'\]; valid keys: \[.*'max_steer'.*degrees"),
    ({"max_steer": 95}, "'max_steer' must be below 90 degrees"),
    ({"max_steer": 0}, "'max_steer' must be a finite number > 0"),
    ({"discrete_steer_reference": "wide"}, "'discrete_steer_reference' must be a finite number > 0"),
    ({"max_lateral_accel": -1}, r"'max_lateral_accel' must be a finite number > 0 \(or null / off"),
    ({"max_lateral_accel": True}, "'max_lateral_accel' must be a finite number"),
    ({"wheelbase": float("inf")}, "'wheelbase' must be a finite number > 0"),
    ([35], "expected a mapping of VehicleParams fields"),
    ({"max_speed": 5.0}, r"acs\[0\].depart_speed 7.0 m/s is above vehicle.max_speed 5.0"),
])
def test_bad_vehicle_blocks_name_the_file_the_key_and_the_choices(tmp_path, vehicle, message):
    path = _scenario_yaml(tmp_path, vehicle=vehicle, relative=False)
    with pytest.raises(ScenarioError, match=message) as err:
        load_scenario(path)
    assert "env_4_vehicle.yaml" in str(err.value)


def test_other_fields_by_name_and_a_world_given_a_car_uses_it_everywhere(tmp_path):
    from cosim.world import World

    sc = load_scenario(_scenario_yaml(tmp_path, vehicle={"max_steer": 30, "length": 4.0}))
    assert math.degrees(sc.vehicle.max_steer) == pytest.approx(30.0) and sc.vehicle.length == 4.0
    car = VehicleParams(length=4.2)
    world = World("env_4", 1, vehicle=car)
    try:
        assert world.vehicle == car == world.scenario.vehicle == world.roadmap.scenario.vehicle
    finally:
        world.close()
