"""Actions (SPEC §2) and the kinematic bicycle."""

import math

import numpy as np
import pytest

from cosim.dynamics import DISCRETE_ACTIONS, VehicleParams, action_to_control, bicycle_step
from cosim.errors import ActionError


def test_discrete_table_is_the_papers():
    assert DISCRETE_ACTIONS.shape == (9, 2)
    assert action_to_control(3, True, "ac_0") == (1.0, 0.0)  # forward
    assert action_to_control(np.int64(7), True, "ac_0") == (-0.5, -0.5)  # brake-left
    assert action_to_control(np.array(5), True, "ac_0") == (0.5, -0.05)


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
