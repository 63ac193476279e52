"""Actions (SPEC §2), the steering mapping (docs/task.md, "Actions and steering") and the
kinematic bicycle."""

import math

import numpy as np
import pytest

from cosim.dynamics import (
    DISCRETE_ACTIONS,
    VehicleParams,
    action_to_control,
    bicycle_step,
    discrete_controls,
)
from cosim.errors import ActionError


def test_discrete_table_is_the_papers():
    assert DISCRETE_ACTIONS.shape == (9, 2)
    assert DISCRETE_ACTIONS[7].tolist() == [-0.5, -0.5]  # brake-left, in the paper's units
    assert DISCRETE_ACTIONS[5].tolist() == [0.5, -0.05]  # forward-left
    # in the bicycle's units (of max_steer): the paper's fractions of CARLA's 70 degrees
    assert action_to_control(3, True, "ac_0") == (1.0, 0.0)  # forward
    assert action_to_control(np.int64(7), True, "ac_0") == (-0.5, -1.0)  # brake-left
    assert action_to_control(np.array(5), True, "ac_0") == pytest.approx((0.5, -0.1))


# action -> wheel angle in degrees (positive = left) the paper's cars had in CARLA
PAPER_ANGLES = {0: 0.0, 1: 35.0, 2: -35.0, 3: 0.0, 4: 0.0, 5: 3.5, 6: -3.5, 7: 35.0, 8: -35.0}


@pytest.mark.parametrize("action,degrees", sorted(PAPER_ANGLES.items()))
def test_discrete_wheel_angles_are_the_papers_at_low_speed(action, degrees):
    p = VehicleParams()
    tb, steer = action_to_control(action, True, "ac_0")
    assert tb == DISCRETE_ACTIONS[action, 0]
    assert math.degrees(p.wheel_angle(steer, 3.0)) == pytest.approx(degrees)


def test_left_turns_tight_enough_for_every_turn_of_the_nets():
    """Discrete "left" at low speed: rear-axle radius below the 5.2 m of the nets' right
    turns (under the old mapping, 17.5 degrees, it was ~8.7 m)."""
    p = VehicleParams()
    radius = p.wheelbase / math.tan(p.wheel_angle(action_to_control(1, True, "a")[1], 3.0))
    assert radius < 4.0
    old = VehicleParams(discrete_steer_reference=p.max_steer)  # fractions of 35 degrees
    old_radius = old.wheelbase / math.tan(old.wheel_angle(action_to_control(1, True, "a", old)[1], 3.0))
    assert old_radius == pytest.approx(8.6, abs=0.1)


def test_the_mapping_clips_to_the_bicycles_limit_and_follows_its_params():
    table = discrete_controls(VehicleParams(max_steer=math.radians(20.0)))
    assert table[1].tolist() == [0.0, -1.0]  # 35 degrees asked, 20 possible: full lock
    assert table[5, 1] == pytest.approx(-3.5 / 20.0)
    assert discrete_controls()[:, 0].tolist() == DISCRETE_ACTIONS[:, 0].tolist()  # throttle kept
    with pytest.raises(ValueError, match="discrete_steer_reference"):
        VehicleParams(discrete_steer_reference=0.0)


def test_continuous_keeps_full_authority():
    """Continuous steer +-1 is max_steer (35 degrees) below the grip limit, unchanged."""
    p = VehicleParams()
    assert action_to_control(np.array([0.2, -1.0]), False, "a") == pytest.approx((0.2, -1.0))
    assert math.degrees(p.wheel_angle(-1.0, 3.0)) == pytest.approx(35.0)
    assert math.degrees(p.wheel_angle(0.5, 3.0)) == pytest.approx(-17.5)


@pytest.mark.parametrize("speed", [6.0, 10.0, 13.89, 25.0])
def test_grip_limits_the_wheel_angle_at_speed(speed):
    p = VehicleParams()
    for steer in (-1.0, 1.0, action_to_control(1, True, "a")[1]):
        delta = float(p.wheel_angle(steer, speed))
        lateral = speed**2 * math.tan(abs(delta)) / p.wheelbase
        assert lateral == pytest.approx(p.max_lateral_accel)  # full lock is beyond grip here
    # small angles are below the limit and pass unchanged
    assert float(p.wheel_angle(0.01, speed)) == pytest.approx(-0.01 * p.max_steer)


def test_a_full_lock_step_at_speed_turns_at_the_grip_limit():
    p = VehicleParams()
    v0 = 14.0
    _, _, h, v = _run(0.0, -1.0, 1, v0=v0)
    v_mean = 0.5 * (v0 + v)
    beta = math.atan(0.5 * p.max_lateral_accel * p.wheelbase / v_mean**2)
    # heading rate v/wb * cos(beta) * tan(delta) with tan(delta) = a_max * wb / v^2
    assert h == pytest.approx(p.max_lateral_accel / v_mean * math.cos(beta) * 0.1, rel=1e-6)


@pytest.mark.parametrize("bad", [9, -1, 2.0, "3", None, np.array([1, 2])])
def test_bad_discrete_actions_name_the_agent(bad):
    with pytest.raises(ActionError, match="ac_4"):
        action_to_control(bad, True, "ac_4")


def test_continuous_clipped_and_nan_rejected():
    assert action_to_control(np.array([3.0, -2.0]), False, "a") == (1.0, -1.0)
    with pytest.raises(ActionError, match="NaN"):
        action_to_control(np.array([np.nan, 0.0]), False, "ac_1")
    with pytest.raises(ActionError, match=r"shape \(2,\)"):
        action_to_control(np.zeros(3), False, "ac_1")
    with pytest.raises(ActionError, match="ac_2"):
        action_to_control(4, False, "ac_2")


def _run(tb, steer, steps, v0=10.0):
    p = VehicleParams()
    x = y = h = np.zeros(1)
    v = np.full(1, v0)
    for _ in range(steps):
        x, y, h, v = bicycle_step(x, y, h, v, np.full(1, tb), np.full(1, steer), p, 0.1)
    return x[0], y[0], h[0], v[0]


def test_straight_coasting_and_throttle():
    x, y, h, v = _run(0.0, 0.0, 10, v0=10.0)
    assert y == 0 and h == 0 and 9.0 < v < 10.0 and 9.0 < x < 10.0  # loses a little speed
    _, _, _, v = _run(1.0, 0.0, 10, v0=10.0)
    assert v > 12.5


def test_negative_steer_turns_left_and_no_reverse():
    _, y, h, _ = _run(0.0, -0.5, 10)
    assert h > 0 and y > 0  # counter-clockwise = left
    _, y, h, _ = _run(0.0, 0.5, 10)
    assert h < 0 and y < 0
    x, _, _, v = _run(-1.0, 0.0, 50, v0=5.0)
    assert v == 0.0 and x > 0  # stops, never backs up
    x2, _, _, _ = _run(-1.0, 0.0, 100, v0=5.0)
    assert x2 == pytest.approx(x)


def test_turning_circle_matches_geometry():
    p = VehicleParams()
    steps = 2000  # long enough to go round more than once at 5 m/s
    x = y = h = np.zeros(1)
    v = np.full(1, 5.0)
    pts = []
    for _ in range(steps):
        x, y, h, v = bicycle_step(x, y, h, v, np.full(1, 0.06), np.full(1, -1.0), p, 0.01)
        pts.append((x[0], y[0]))
    pts = np.array(pts)
    radius = (pts[:, 1].max() - pts[:, 1].min()) / 2
    beta = math.atan(0.5 * math.tan(p.max_steer))
    expected = p.wheelbase / (math.tan(p.max_steer) * math.cos(beta))
    assert radius == pytest.approx(expected, rel=0.05)
