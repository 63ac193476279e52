"""The state track's observation: a low-dimensional float32 vector per AC, read from the
:class:`~cosim.world.World` (no camera; docs/task.md, "Observation", "The state track").

``cosim.parallel_env(..., obs="state")`` (and ``cosim train --obs state``) gives each AC this
vector instead of its camera image, with the PyBullet mirror never built
(``CosimParallelEnv(camera=False)``): what MetaDrive and highway-env train on, the benchmark's
decision-making track and its perception ablation. A policy trained on it that drives one AC
of a shared test environment (cameras on where another AC reads them, else off:
eval/testing/rollout.py ``use_cameras``) builds the same vector with :func:`agent_state`
(eval/testing/rollout.py ``StatePolicy``).

The vector (:data:`STATE_DIM` = 65 numbers, in this order; :data:`STATE_LAYOUT` names each
block's slice). Ego frame: x forward, y to the left, origin the AC's centre. Every number is
clipped to the bounds of :func:`state_space`.

====  ===================  ===========================================================
 0    speed                forward speed / 13.89 m/s (the speed limit), 0..1.8
 1    lateral              signed distance from the route centreline / 5 m, + = the AC
                           is left of it, clipped to -1..1
 2-3  heading error        sin, cos of (AC heading - route heading where it projects)
 4-11 path ahead           the route centreline 5, 10, 20 and 30 m further along the route
                           than the AC's projection, each (x, y) in the ego frame / 30 m
                           (-1.5..1.5; on a straight road, centred and aligned: (d/30, 0))
 12   goal                 distance to the goal along the route / the spawn's (1 at the
                           spawn, 0 at the goal), 0..1
 13-14 previous control    (throttle(+)/brake(-), steer) applied at the last step, -1..1
                           (0, 0 after a reset)
 15-19 signal              the next traffic light on the route within 60 m whose stop line
                           the AC's centre has not passed: one-hot (none, red, yellow,
                           green), then the gap from the AC's front bumper to the stop line
                           / 60 m (0..1; 1 when none). SUMO's r/R/u read red, y/Y yellow,
                           G/g/s green, o/O (off) none
 20-49 vehicles            the 6 nearest other vehicles (ACs and SUMO's cars) whose centres
                           are within 50 m, nearest first, 5 numbers each: present (1, or
                           0 for an empty slot, all zeros), (x, y) of the centre in the ego
                           frame / 50 m (-1..1), velocity relative to the AC's in the ego
                           frame / 27.78 m/s (two cars at the limit head-on: 1; -2..2)
 50-64 pedestrians         the 3 nearest pedestrians within 50 m, the same 5 numbers each
====  ===================  ===========================================================

Cost: a route projection (a grid lookup), a few interpolations and one distance matrix per
step for all ACs at once (numpy), against the PyBullet render that is most of the camera
env's step time (docs/benchmarks.md, "The state track's speed").
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import gymnasium
import numpy as np

SPEED_SCALE = 13.89
"""m/s that read 1.0 in the speed (the scenarios' speed limit, as the nav measurements)."""
MAX_SPEED = 25.0
"""The learning car's top speed (cosim.dynamics.VehicleParams.max_speed): the speed's bound."""
LATERAL_SCALE = 5.0
"""Metres of lateral offset from the route centreline that read 1.0 (clipped there)."""
PATH_AHEAD = (5.0, 10.0, 20.0, 30.0)
"""Metres along the route, past the AC's projection, of the centreline points it observes."""
PATH_SCALE = 30.0
"""Metres that read 1.0 in the path points' ego-frame coordinates."""
SIGNAL_RANGE = 60.0
"""Metres ahead (front bumper to stop line) within which the next traffic light is observed."""
SIGNAL_STATES = ("none", "red", "yellow", "green")
"""The next signal's one-hot, in this order."""
_SIGNAL_OF_CHAR = {"r": 1, "R": 1, "u": 1, "y": 2, "Y": 2, "G": 3, "g": 3, "s": 3}
NEIGHBOUR_RANGE = 50.0
"""Metres (centre to centre) within which other vehicles and pedestrians are observed; also
the scale of their ego-frame positions."""
REL_SPEED_SCALE = 2 * SPEED_SCALE
"""m/s of relative velocity that read 1.0 (two cars at the speed limit, head-on)."""
K_VEHICLES = 6
"""Other vehicles observed (nearest first)."""
K_PEDESTRIANS = 3
"""Pedestrians observed (nearest first)."""
NEIGHBOUR_FEATURES = ("present", "x", "y", "vx", "vy")

_EGO = 4
_PATH = 2 * len(PATH_AHEAD)
_SIG = len(SIGNAL_STATES) + 1


def _layout() -> dict[str, slice]:
    sizes = (("speed", 1), ("lateral", 1), ("heading_error", 2), ("path", _PATH), ("goal", 1),
             ("control", 2), ("signal", _SIG), ("vehicles", K_VEHICLES * len(NEIGHBOUR_FEATURES)),
             ("pedestrians", K_PEDESTRIANS * len(NEIGHBOUR_FEATURES)))
    out, start = {}, 0
    for name, n in sizes:
        out[name] = slice(start, start + n)
        start += n
    return out


STATE_LAYOUT: dict[str, slice] = _layout()
"""Block name -> its slice of the state vector (the module docstring's table)."""
STATE_DIM = STATE_LAYOUT["pedestrians"].stop
"""Length of the state vector (65)."""


def _bounds() -> tuple[np.ndarray, np.ndarray]:
    low, high = np.zeros(STATE_DIM, np.float32), np.ones(STATE_DIM, np.float32)
    L = STATE_LAYOUT
    high[L["speed"]] = MAX_SPEED / SPEED_SCALE
    low[L["lateral"]] = -1.0
    low[L["heading_error"]] = -1.0
    low[L["path"]], high[L["path"]] = -1.5, 1.5
    low[L["control"]] = -1.0
    for block in ("vehicles", "pedestrians"):
        lo, hi = low[L[block]].reshape(-1, 5), high[L[block]].reshape(-1, 5)
        lo[:, 1:3], lo[:, 3:5], hi[:, 3:5] = -1.0, -2.0, 2.0
    return low, high


STATE_LOW, STATE_HIGH = _bounds()


def state_space() -> gymnasium.spaces.Box:
    """The space of one AC's state vector: ``Box(STATE_LOW, STATE_HIGH, (65,), float32)``."""
    return gymnasium.spaces.Box(STATE_LOW.copy(), STATE_HIGH.copy(), dtype=np.float32)


def is_state_space(space) -> bool:
    """Whether ``space`` is the state track's (a checkpoint trained with ``--obs state``)."""
    return (isinstance(space, gymnasium.spaces.Box) and tuple(space.shape) == (STATE_DIM,)
            and np.issubdtype(space.dtype, np.floating))


def _neighbours(ego_xy: np.ndarray, ego_h: np.ndarray, ego_v: np.ndarray, xy: np.ndarray,
                heading: np.ndarray, speed: np.ndarray, k: int, exclude: np.ndarray | None) -> np.ndarray:
    """(n, k, 5) present, x, y, vx, vy of the ``k`` nearest of the actors (xy, heading, speed)
    within NEIGHBOUR_RANGE of each of n egos; ``exclude`` (n, m) bool masks actors (the ego)."""
    n = len(ego_xy)
    out = np.zeros((n, k, 5))
    if len(xy) == 0 or k == 0:
        return out
    rel = xy[None, :, :] - ego_xy[:, None, :]  # (n, m, 2)
    dist = np.hypot(rel[..., 0], rel[..., 1])
    dist = np.where(dist <= NEIGHBOUR_RANGE, dist, np.inf)
    if exclude is not None:
        dist[exclude] = np.inf
    kk = min(k, xy.shape[0])
    order = np.argsort(dist, axis=1, kind="stable")[:, :kk]  # (n, kk)
    rows = np.arange(n)[:, None]
    present = np.isfinite(dist[rows, order])
    c, s = np.cos(ego_h)[:, None], np.sin(ego_h)[:, None]
    rx, ry = rel[rows, order, 0], rel[rows, order, 1]
    vx = speed[order] * np.cos(heading[order]) - (ego_v[:, None] * c)
    vy = speed[order] * np.sin(heading[order]) - (ego_v[:, None] * s)
    block = np.stack([np.ones_like(rx), (rx * c + ry * s) / NEIGHBOUR_RANGE, (-rx * s + ry * c) / NEIGHBOUR_RANGE,
                      (vx * c + vy * s) / REL_SPEED_SCALE, (-vx * s + vy * c) / REL_SPEED_SCALE], axis=2)
    out[:, :kk] = np.where(present[..., None], block, 0.0)
    return out


def state_vectors(world, agents: Sequence[str],
                  controls: Mapping[str, tuple[float, float]] | None = None) -> np.ndarray:
    """The state vectors (len(agents), STATE_DIM) float32 of active ACs ``agents`` of ``world``
    (a cosim.world.World after a reset or step), in the order of the module docstring;
    ``controls``: each AC's previous (throttle/brake, steer), (0, 0) where missing."""
    n = len(agents)
    out = np.zeros((n, STATE_DIM))
    if n == 0:
        return out.astype(np.float32)
    controls = controls or {}
    snap = world.snapshot
    half_length = world.vehicle.length / 2
    ego = np.array([world.ac_state(a) for a in agents], dtype=float)  # x, y, heading, speed
    L = STATE_LAYOUT
    ahead = np.asarray(PATH_AHEAD)
    for i, a in enumerate(agents):
        x, y, h, v = ego[i]
        route = world.route(a)
        path = route.path
        s = float(route.arc_length(x, y))
        query = np.clip(np.concatenate([[s], s + ahead]), 0.0, path.length)
        qx = np.interp(query, path.cumlen, path.points[:, 0])
        qy = np.interp(query, path.cumlen, path.points[:, 1])
        rh = path.heading_at(s)
        dx, dy = x - qx[0], y - qy[0]
        out[i, L["speed"]] = v / SPEED_SCALE
        out[i, L["lateral"]] = (-dx * math.sin(rh) + dy * math.cos(rh)) / LATERAL_SCALE
        err = h - rh
        out[i, L["heading_error"]] = (math.sin(err), math.cos(err))
        px, py = qx[1:] - x, qy[1:] - y
        c, sn = math.cos(h), math.sin(h)
        out[i, L["path"]] = np.stack([px * c + py * sn, -px * sn + py * c], axis=1).ravel() / PATH_SCALE
        out[i, L["goal"]] = (route.goal_s - s) / max(route.goal_s - route.spawn_s, 1e-6)
        out[i, L["control"]] = controls.get(a, (0.0, 0.0))
        signal = np.zeros(_SIG)
        signal[0], signal[-1] = 1.0, 1.0
        for stop_s, tls, link in route.signals:  # ordered along the route
            if stop_s < s:
                continue  # the AC's centre is past this stop line
            gap = max(stop_s - s - half_length, 0.0)
            if gap <= SIGNAL_RANGE:
                state = snap.signals.get(tls, "")
                kind = _SIGNAL_OF_CHAR.get(state[link], 0) if link < len(state) else 0
                signal[:] = 0.0
                signal[kind], signal[-1] = 1.0, gap / SIGNAL_RANGE
            break
        out[i, L["signal"]] = signal
    ids = np.asarray(snap.vehicle_ids, dtype=object)
    exclude = ids[None, :] == np.asarray(agents, dtype=object)[:, None] if len(ids) else None
    out[:, L["vehicles"]] = _neighbours(ego[:, :2], ego[:, 2], ego[:, 3], snap.vehicle_xy,
                                        snap.vehicle_heading, snap.vehicle_speed, K_VEHICLES,
                                        exclude).reshape(n, -1)
    out[:, L["pedestrians"]] = _neighbours(ego[:, :2], ego[:, 2], ego[:, 3], snap.person_xy,
                                           snap.person_heading, snap.person_speed, K_PEDESTRIANS,
                                           None).reshape(n, -1)
    return np.clip(out, STATE_LOW, STATE_HIGH).astype(np.float32)


def agent_state(env, agent: str) -> np.ndarray:
    """The state vector of AC ``agent`` of a cosim env (or a wrapper of one) as it stands
    (after its last reset or step): what the env gives that AC with ``obs="state"``, for a
    policy trained on the state that drives one AC of a shared test env."""
    base = env.unwrapped
    return state_vectors(base.world, [agent], base.last_controls)[0]
