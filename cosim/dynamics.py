"""Learning-car actions and ego dynamics (a kinematic bicycle, deterministic).

Actions follow SPEC §2. Discrete(9) is the paper's table of (throttle/brake,
steer) pairs; Box(-1, 1, (2,)) is (throttle(+)/brake(-), steer). Negative steer
turns left (CARLA's convention, kept from the paper's code). Reverse is disabled:
braking stops the car, never backs it up.

Steering (docs/task.md, "Actions and steering"): a continuous steer of +-1 is the
bicycle's wheel limit ``VehicleParams.max_steer`` (35 degrees); the discrete table's
steer fractions are of CARLA's 70 degree wheel limit, the one the paper's table was
written for (``VehicleParams.discrete_steer_reference``), so "left" is 35 degrees and
"forward-left" 3.5 degrees, as the paper's cars had them. At speed every wheel angle,
discrete or continuous, is limited by grip (``VehicleParams.max_lateral_accel``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from cosim.errors import ActionError

# (throttle(+)/brake(-), steer) per discrete action, from the paper's published code; the
# steer column is a fraction of VehicleParams.discrete_steer_reference (CARLA's 70 degrees),
# not of max_steer: discrete_controls() gives the table in the units bicycle_step takes.
DISCRETE_ACTIONS = np.array(
    [
        [0.0, 0.0],  # 0 coast
        [0.0, -0.5],  # 1 left
        [0.0, 0.5],  # 2 right
        [1.0, 0.0],  # 3 forward
        [-0.5, 0.0],  # 4 brake
        [0.5, -0.05],  # 5 forward-left
        [0.5, 0.05],  # 6 forward-right
        [-0.5, -0.5],  # 7 brake-left
        [-0.5, 0.5],  # 8 brake-right
    ],
    dtype=np.float64,
)
ACTION_NAMES = (
    "coast", "left", "right", "forward", "brake",
    "forward-left", "forward-right", "brake-left", "brake-right",
)


@dataclass(frozen=True)
class VehicleParams:
    """Geometry and limits of a learning car (a mid-size sedan)."""

    length: float = 4.5
    """Metres bumper to bumper."""
    width: float = 1.8
    """Metres."""
    wheelbase: float = 2.7
    """Metres between axles."""
    max_steer: float = math.radians(35.0)
    """Radians of front-wheel angle at steer = +-1 (a continuous action's full authority:
    rear-axle turning radius 3.9 m, tighter than every turn of the bundled nets, whose
    right turns need ~5.2 m and roundabout entries and exits ~6.5 m)."""
    discrete_steer_reference: float = math.radians(70.0)
    """Radians of wheel angle that the discrete table's steer fractions are of.

    The paper's table (+-0.5 left/right, +-0.05 forward-left/right) was written for
    CARLA, whose default wheel limit is 70 degrees: its "left" turned the wheels ~35
    degrees. Taken as fractions of our 35 degree ``max_steer`` instead, "left" would be
    17.5 degrees (radius ~8.7 m) and no discrete policy could take a right turn or a
    roundabout exit. So discrete steer ``f`` commands ``f * discrete_steer_reference``,
    clipped to ``max_steer``: left/right 35 degrees, forward-left/right 3.5 degrees
    (docs/task.md, "Actions and steering")."""
    max_lateral_accel: float = 8.0
    """m/s^2 of lateral acceleration the tyres can give (~0.8 g, dry asphalt): at speed v
    the wheel angle is limited to ``atan(max_lateral_accel * wheelbase / v**2)``, for
    discrete and continuous actions alike. It binds above ~5.6 m/s at full lock and keeps
    the kinematic bicycle from turning at several g (full lock at 14 m/s would be 5 g);
    every turn of the nets, taken at the autopilot's 2 m/s^2, is far below it. ``math.inf``:
    no grip limit (the steering before issue 25; a scenario's ``vehicle:`` block writes it
    ``max_lateral_accel: null``)."""
    max_accel: float = 3.5
    """m/s^2 at full throttle."""
    max_brake: float = 8.0
    """m/s^2 at full brake."""
    max_speed: float = 25.0
    """m/s, a hard cap (90 km/h)."""
    rolling_decel: float = 0.3
    """m/s^2 lost when coasting (rolling resistance, engine braking)."""
    drag: float = 0.0015
    """Quadratic drag coefficient, 1/m (so top speed at full throttle is ~48 m/s before the cap)."""

    def __post_init__(self) -> None:
        for name in ("length", "width", "wheelbase", "max_steer", "discrete_steer_reference",
                     "max_lateral_accel", "max_accel", "max_brake", "max_speed"):
            if getattr(self, name) <= 0:
                raise ValueError(f"VehicleParams.{name} must be > 0, got {getattr(self, name)}")
        if self.max_steer >= math.pi / 2:
            raise ValueError(f"VehicleParams.max_steer must be below pi/2 rad (90 degrees), "
                             f"got {self.max_steer}")

    def wheel_angle(self, steer, speed):
        """Front-wheel angle (radians, positive = left) for steer commands in [-1, 1] of
        ``max_steer`` at the given speeds (m/s), after the grip limit ``max_lateral_accel``."""
        delta = -np.asarray(steer, dtype=float) * self.max_steer
        v2 = np.maximum(np.asarray(speed, dtype=float) ** 2, 1e-9)
        grip = np.arctan(self.max_lateral_accel * self.wheelbase / v2)
        return np.clip(delta, -grip, grip)


def discrete_controls(params: VehicleParams | None = None) -> np.ndarray:
    """The discrete table in bicycle_step's units: (throttle/brake, steer of ``max_steer``).

    Steer fractions of the table are of ``params.discrete_steer_reference`` (docs/task.md,
    "Actions and steering"); with the defaults: left/right -1/+1, forward-left/right -0.1/+0.1.
    The array is read-only (one per ``params``, cached).
    """
    return _discrete_controls(params or _DEFAULT_PARAMS)


@functools.lru_cache(maxsize=16)
def _discrete_controls(params: VehicleParams) -> np.ndarray:
    table = DISCRETE_ACTIONS.copy()
    scale = params.discrete_steer_reference / params.max_steer
    table[:, 1] = np.clip(table[:, 1] * scale, -1.0, 1.0)
    table.flags.writeable = False
    return table


_DEFAULT_PARAMS = VehicleParams()


def action_to_control(action, discrete: bool, agent: str,
                      params: VehicleParams | None = None) -> tuple[float, float]:
    """One agent's action -> (throttle/brake in [-1, 1], steer in [-1, 1] of ``max_steer``).

    A discrete action is its row of :func:`discrete_controls` (``params``, default
    :class:`VehicleParams`). Continuous actions outside [-1, 1] are clipped; NaN/inf,
    wrong shapes and out-of-range discrete actions raise :class:`ActionError` naming
    the agent.
    """
    if discrete:
        if isinstance(action, np.ndarray):
            if action.size != 1 or not np.issubdtype(action.dtype, np.integer):
                raise ActionError(
                    f"agent {agent!r}: expected an int in 0..8 for its Discrete(9) action space, "
                    f"got an array of shape {action.shape} and dtype {action.dtype}"
                )
            action = int(action.reshape(()))
        if isinstance(action, bool) or not isinstance(action, int | np.integer):
            raise ActionError(
                f"agent {agent!r}: expected an int in 0..8 for its Discrete(9) action space, got {action!r}"
            )
        if not 0 <= int(action) < len(DISCRETE_ACTIONS):
            raise ActionError(f"agent {agent!r}: discrete action {action} is outside Discrete(9) (0..8)")
        tb, steer = discrete_controls(params)[int(action)]
        return float(tb), float(steer)
    try:
        arr = None if isinstance(action, int | bool) else np.asarray(action)
    except ValueError:  # ragged nested lists
        arr = np.asarray(None)
    if arr is not None and arr.dtype.kind not in "biuf":  # strings, dicts, None, objects
        raise ActionError(
            f"agent {agent!r}: expected two numbers (throttle/brake, steer) for its Box(-1, 1, (2,)) "
            f"action space, got {action!r}"
        )
    if arr is not None:
        arr = arr.astype(np.float64)
    if arr is None or arr.shape != (2,):
        shape = getattr(arr, "shape", type(action).__name__)
        raise ActionError(
            f"agent {agent!r}: expected a float array of shape (2,) = (throttle/brake, steer) "
            f"for its Box(-1, 1, (2,)) action space, got {shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ActionError(f"agent {agent!r}: action {arr.tolist()} contains NaN or inf")
    arr = np.clip(arr, -1.0, 1.0)
    return float(arr[0]), float(arr[1])


def bicycle_step(
    x: np.ndarray, y: np.ndarray, heading: np.ndarray, speed: np.ndarray,
    throttle_brake: np.ndarray, steer: np.ndarray, params: VehicleParams, dt: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Advance N cars one step of the kinematic bicycle model (rear-axle free, centre reference).

    Positive throttle_brake accelerates, negative brakes; speed never goes below 0.
    Negative steer turns left (counter-clockwise); the wheel angle is
    :meth:`VehicleParams.wheel_angle` at the step's mean speed (grip-limited).
    """
    accel = np.where(
        throttle_brake >= 0,
        throttle_brake * params.max_accel,
        throttle_brake * params.max_brake,
    )
    moving = speed > 0
    resist = np.where(moving, params.rolling_decel + params.drag * speed * speed, 0.0)
    new_speed = np.clip(speed + (accel - resist) * dt, 0.0, params.max_speed)
    v = 0.5 * (speed + new_speed)  # trapezoidal: exact for constant acceleration
    delta = params.wheel_angle(steer, v)
    # slip angle at the centre of a kinematic bicycle with the centre mid-wheelbase
    beta = np.arctan(0.5 * np.tan(delta))
    new_heading = heading + v / params.wheelbase * np.cos(beta) * np.tan(delta) * dt
    mid = 0.5 * (heading + new_heading)
    new_x = x + v * np.cos(mid + beta) * dt
    new_y = y + v * np.sin(mid + beta) * dt
    new_heading = (new_heading + np.pi) % (2 * np.pi) - np.pi
    return new_x, new_y, new_heading, new_speed
