"""Learning-car actions and ego dynamics (a kinematic bicycle, deterministic).

Actions follow SPEC §2. Discrete(9) is the paper's table of (throttle/brake,
steer) pairs; Box(-1, 1, (2,)) is (throttle(+)/brake(-), steer). Negative steer
turns left (CARLA's convention, kept from the paper's code). Reverse is disabled:
braking stops the car, never backs it up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cosim.errors import ActionError

# (throttle(+)/brake(-), steer) per discrete action, from the paper's published code.
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
    """Radians of front-wheel angle at steer = +-1."""
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
        for name in ("length", "width", "wheelbase", "max_steer", "max_accel", "max_brake", "max_speed"):
            if getattr(self, name) <= 0:
                raise ValueError(f"VehicleParams.{name} must be > 0, got {getattr(self, name)}")


def action_to_control(action, discrete: bool, agent: str) -> tuple[float, float]:
    """One agent's action -> (throttle/brake in [-1, 1], steer in [-1, 1]).

    Continuous actions outside [-1, 1] are clipped; NaN/inf, wrong shapes and
    out-of-range discrete actions raise :class:`ActionError` naming the agent.
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
        tb, steer = DISCRETE_ACTIONS[int(action)]
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
    Negative steer turns left (counter-clockwise).
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
    delta = -steer * params.max_steer
    # slip angle at the centre of a kinematic bicycle with the centre mid-wheelbase
    beta = np.arctan(0.5 * np.tan(delta))
    new_heading = heading + v / params.wheelbase * np.cos(beta) * np.tan(delta) * dt
    mid = 0.5 * (heading + new_heading)
    new_x = x + v * np.cos(mid + beta) * dt
    new_y = y + v * np.sin(mid + beta) * dt
    new_heading = (new_heading + np.pi) % (2 * np.pi) - np.pi
    return new_x, new_y, new_heading, new_speed
