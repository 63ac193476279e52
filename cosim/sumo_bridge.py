"""The SUMO side of the co-simulation: libsumo in-process, one simulation per process.

SUMO runs the background cars and pedestrians. Each learning car (AC) is also a
SUMO vehicle of its own vType, on a route to its goal (so foes see it and yield),
with speed mode 0, moved every step with ``moveToXY(keepRoute=2)`` so it can leave
the road. We read every actor near the region with two context subscriptions on
POIs at the region centre: one call per step for cars, one for pedestrians.

SUMO positions are front-bumper centres and compass angles (degrees clockwise
from north); the bridge converts to vehicle centres and radians counter-clockwise
from east, the convention of the rest of cosim.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import itertools
import logging
import math
import os
import tempfile
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim.errors import SimulatorUnavailable, SumoError
from cosim.geometry import Polyline
from cosim.scenario import Scenario

log = logging.getLogger(__name__)

# libsumo is one simulation per process: remember which bridge owns it, to fail clearly.
_owner: weakref.ReferenceType | None = None
_labels = itertools.count()  # unique TraCI connection labels
_warned_second = False  # the second-simulation warning was logged in this process

PERSON_RADIUS = 0.3  # metres; a person's footprint is a circle
_VAR_POSITION, _VAR_ANGLE, _VAR_SPEED, _VAR_TYPE = 0x42, 0x43, 0x40, 0x4F
_VAR_ROAD_ID, _VAR_LANE_ID, _VAR_LANEPOSITION = 0x50, 0x51, 0x56
GRIDLOCK_WAIT = 15.0  # seconds a background car may stand inside a junction (see _clear_gridlock)
GRIDLOCK_CHECK_EVERY = 10  # steps between checks
# a background car within GATE_REACH m of a junction waits there while an AC's body lies on
# its path through the junction (within half its width + GATE_MARGIN m): see gate_entries
GATE_REACH = 12.0
GATE_MARGIN = 0.3
GATE_NEAR = 25.0  # metres: only cars this close to an AC are checked
GATE_DECEL = 4.0  # m/s^2: a car that cannot stop before the junction at this rate is let go
GATE_AHEAD = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)  # seconds: where an AC will be, for people
# with Scenario.cars_see_acs, a background car on a lane also waits while an AC's body lies on
# its lane ahead, from its front to its stopping distance at GATE_DECEL + SEE_BUFFER m on (the
# margin for a car that brakes at its own rate from one step later): see _cars_seeing
SEE_BUFFER = 8.0
SEE_NEAR = 45.0  # metres: the cars checked for it (a car at 16 m/s, the bundled cars' top speed, needs 40)
# and a person (anywhere: sidewalk, walking area, crossing) waits while a moving AC's body, grown
# by its radius + GATE_MARGIN, lies on its next PERSON_AHEAD m of walk: see _people_seeing
PERSON_AHEAD = 1.5
PERSON_STEP = 0.25  # metres between the points of that walk checked
_CMD_GET_VEHICLE_VARIABLE, _CMD_GET_PERSON_VARIABLE = 0xA4, 0xAE


def _libsumo():
    try:
        import sumo

        os.environ.setdefault("SUMO_HOME", sumo.SUMO_HOME)
        import libsumo
    except ImportError as exc:  # reported when the simulation starts, never at import time
        raise SimulatorUnavailable(
            f"libsumo is not importable ({exc}); install it with "
            "`pip install eclipse-sumo==1.28.0 libsumo==1.28.0`"
        ) from exc
    return libsumo


def _near(actors: list, pts: np.ndarray, radius: float = GATE_NEAR) -> list:
    """The (id, subscription results) of `actors` within `radius` m of any of `pts` (k, 2)."""
    if not actors or not len(pts):
        return []
    at = np.array([var[_VAR_POSITION] for _, var in actors], dtype=float)
    d2 = ((at[:, None, :] - pts[None, :, :]) ** 2).sum(axis=2).min(axis=1)
    return [a for a, close in zip(actors, d2 <= radius ** 2, strict=True) if close]


def _along_beside(path: Polyline, pts: np.ndarray, reach: np.ndarray, start: float = 0.0,
                  end: float = math.inf) -> np.ndarray:
    """Each of `pts`' (k, 2) arc length along `path` where it lies beside it within its `reach`
    (k,), between arc lengths `start` and `end` (not beyond the path's ends: a point past an end
    is another path's); inf where it does not."""
    at = np.full(len(pts), np.inf)
    lo, hi = path.points.min(axis=0), path.points.max(axis=0)
    box = np.all((pts >= lo - reach[:, None]) & (pts <= hi + reach[:, None]), axis=1)
    if box.any():
        along, lat = path.project_many(pts[box])
        hit = (along > max(start, 0.0)) & (along < min(end, path.length)) & (np.abs(lat) < reach[box])
        at[np.flatnonzero(box)[hit]] = along[hit]
    return at


def _touches(path: Polyline, pts: np.ndarray, reach: np.ndarray) -> bool:
    """Whether any of `pts` lies beside `path` (not beyond its ends) within its `reach`."""
    return bool(np.isfinite(_along_beside(path, pts, reach)).any())


def sumo_to_heading(angle_deg: float | np.ndarray):
    """SUMO compass angle (deg, clockwise from north) -> radians counter-clockwise from east."""
    return np.radians(90.0 - np.asarray(angle_deg))


def heading_to_sumo(heading: float) -> float:
    return (90.0 - math.degrees(heading)) % 360.0


@dataclass
class Snapshot:
    """Every actor near the region at one instant (centres, radians, metres).

    Cars include the ACs (``is_ac``); ``vehicle_ids`` of ACs are their agent names.
    """

    time: float
    vehicle_ids: list[str]
    vehicle_xy: np.ndarray  # (n, 2) centres
    vehicle_heading: np.ndarray  # (n,)
    vehicle_speed: np.ndarray  # (n,)
    vehicle_length: np.ndarray  # (n,)
    vehicle_width: np.ndarray  # (n,)
    vehicle_is_ac: np.ndarray  # (n,) bool
    person_ids: list[str]
    person_xy: np.ndarray  # (m, 2)
    person_heading: np.ndarray  # (m,)
    person_speed: np.ndarray  # (m,)
    signals: dict[str, str] = dataclasses.field(default_factory=dict)
    """Traffic light id -> SUMO state string (one char per link) for the ACs' routes."""

    def actors(self) -> list[Actor]:
        """The snapshot as a flat list, for the mirror and for people."""
        out = [
            Actor(vid, "ac" if ac else "car", float(x), float(y), float(h), float(ln), float(w))
            for vid, (x, y), h, ln, w, ac in zip(
                self.vehicle_ids,
                self.vehicle_xy,
                self.vehicle_heading,
                self.vehicle_length,
                self.vehicle_width,
                self.vehicle_is_ac,
                strict=True,
            )
        ]
        out += [
            Actor(pid, "pedestrian", float(x), float(y), float(h), 2 * PERSON_RADIUS, 2 * PERSON_RADIUS)
            for pid, (x, y), h in zip(self.person_ids, self.person_xy, self.person_heading, strict=True)
        ]
        return out


@dataclass(frozen=True)
class Actor:
    """One actor of a snapshot: id, kind (ac / car / pedestrian), pose, size."""

    id: str
    kind: str
    x: float
    y: float
    heading: float
    length: float
    width: float


class SumoBridge:
    """Start / reset / step / close one SUMO simulation through libsumo.

    Usable as a context manager; ``close()`` is idempotent. Every libsumo failure
    surfaces as a :class:`SumoError` carrying SUMO's message, after SUMO is closed.
    """

    def __init__(self, scenario: Scenario, *, background: bool = True, pedestrians: bool = True,
                 backend: str = "auto"):
        if backend not in ("auto", "libsumo", "traci", "gui"):
            raise ValueError(
                f"backend must be 'auto', 'libsumo', 'traci' or 'gui' (sumo-gui viewer), got {backend!r}"
            )
        if backend == "gui" and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise SimulatorUnavailable(
                "sumo-gui (--gui) needs a display, and neither DISPLAY nor WAYLAND_DISPLAY is set; "
                "run without --gui, or with a display (ssh -X, xvfb-run)"
            )
        self.scenario = scenario
        self.backend = backend
        self._errors: tuple[type[BaseException], ...] = (RuntimeError,)
        self.background = background and scenario.background.enabled
        self.pedestrians = pedestrians and scenario.pedestrians
        self._ls = None
        self._running = False
        self._type_size: dict[str, tuple[float, float]] = {}
        self._acs: dict[str, tuple[str, int, float]] = {}  # id -> (route id, lane, pos)
        self._pinned: dict[str, tuple[float, float, str]] = {}  # person id -> (x, y, edge)
        self._steps = 0  # SUMO steps since the last start (paces the gridlock check)
        self._held: set[str] = set()  # background cars gate_entries holds before a junction
        self._held_people: set[str] = set()  # and people it holds before a crossing
        self._next: dict[tuple[str, str], str | None] = {}  # (car, lane) -> its next internal lane
        self._half: dict[str, float] = {}  # car or crossing -> half its width
        self._min_gap: dict[str, float] = {}  # car -> its minGap (cached with its half width)
        self._lane_length: dict[str, float] = {}
        self._paths: dict[str, Polyline] = {}  # internal lane -> its path through the junction
        self._lanes: dict[str, Polyline] = {}  # lane -> its centre line (Scenario.cars_see_acs)
        self.time = 0.0

    # -- lifecycle -----------------------------------------------------------
    def command(self, seed: int) -> list[str]:
        sc = self.scenario
        routes = list(sc.demand if self.background else ()) + list(
            sc.pedestrian_demand if self.pedestrians else ()
        )
        cmd = [
            "sumo",
            "--net-file", str(sc.net),
            "--step-length", repr(sc.dt),
            "--seed", str(int(seed) % (2**31)),
            "--collision.action", "none",  # we decide collisions ourselves
            "--time-to-teleport", "-1",
            "--time-to-teleport.disconnected", "-1",
            "--scale", repr(sc.background.scale),
            "--no-step-log", "true",
            "--no-warnings", "true",
            "--duration-log.disable", "true",
        ]
        if routes:
            cmd += ["--route-files", ",".join(str(p) for p in routes)]
        if sc.additional:
            cmd += ["--additional-files", ",".join(str(p) for p in sc.additional)]
        return cmd

    def start(self, seed: int) -> None:
        """Start (or restart with a new seed) the simulation and subscribe to the region.

        The first simulation of a process runs in-process through libsumo (fast). libsumo
        holds one simulation per process, so with ``backend="auto"`` a second one runs in
        a child process's libsumo instead, each call sent over a private socket pair
        (``cosim/sumo_process.py``: same results, slower; a warning says so), never through
        TraCI, whose SUMO listens on a TCP port of every interface. ``backend="libsumo"``
        refuses a second one; ``"traci"`` and ``"gui"`` (sumo-gui) use TraCI as asked.
        """
        if self._running:
            try:
                self._ls.load(self.command(seed)[1:])
                self._subscribe()
            except self._errors as exc:
                self._fail(f"SUMO could not restart scenario {self.scenario.name!r}", exc, seed)
            self._acs.clear()
            self._pinned.clear()
            self._held.clear()
            self._held_people.clear()
            self._next.clear()
            self._half.clear()
            self._min_gap.clear()
            self.time = 0.0
            self._steps = 0
            return
        global _owner
        owner = _owner() if _owner is not None else None
        libsumo_busy = owner is not None and owner is not self and owner._running
        if libsumo_busy and self.backend == "libsumo":
            raise SumoError(
                "libsumo runs one SUMO simulation per process and another environment in this "
                "process still has one open; close() it first, use backend='traci', or run "
                "environments in worker processes (one simulation per process)"
            )
        try:
            if self.backend in ("traci", "gui"):
                self._start_traci(seed)
            elif libsumo_busy:
                self._start_process(seed)
            else:
                ls = _libsumo()
                self._ls, self._errors = ls, (ls.TraCIException,)
                self._running = True  # set first: a failed start still needs close()
                _owner = weakref.ref(self)
                ls.start(self.command(seed))
            self._subscribe()
        except SimulatorUnavailable:
            raise
        except Exception as exc:  # libsumo raises TraCIException, FatalTraCIError, RuntimeError
            self._fail(f"SUMO could not start scenario {self.scenario.name!r}", exc, seed)
        self._acs.clear()
        self._pinned.clear()
        self._held.clear()
        self._held_people.clear()
        self._next.clear()
        self._half.clear()
        self._min_gap.clear()
        self._paths.clear()
        self._lanes.clear()
        self._lane_length.clear()
        self.time = 0.0
        self._steps = 0

    def _start_process(self, seed: int) -> None:
        """A second simulation of this process: libsumo in a child process (cosim/sumo_process.py)."""
        _libsumo()  # sets SUMO_HOME from the wheel (the child inherits it), reports a missing install
        from cosim.sumo_process import SumoCallError, SumoProcess

        global _warned_second
        if not _warned_second:  # once per process: a training run's validation env is one at
            _warned_second = True  # every checkpoint
            log.warning(
                "a second SUMO simulation in this process runs in a child process (slower than "
                "in-process libsumo); use one environment per process for speed"
            )
        self._errors = (SumoCallError,)
        self._running = True  # set first: a failed start still needs close()
        self._ls = SumoProcess()
        self._ls.start(self.command(seed))

    def _start_traci(self, seed: int) -> None:
        _libsumo()  # sets SUMO_HOME from the wheel, reports a missing install
        import sumo
        import traci
        import traci.connection
        from traci.exceptions import FatalTraCIError, TraCIException

        gui = self.backend == "gui"
        binary = str(Path(sumo.__file__).parent / "bin" / ("sumo-gui" if gui else "sumo"))
        label = f"cosim-{id(self)}-{next(_labels)}"
        # libsumo's import replaces traci.exceptions.TraCIException with its own class, while
        # traci.connection raises the one it imported first: catch both
        self._errors = (TraCIException, traci.connection.TraCIException, FatalTraCIError)
        self._running = True
        extra = ["--start", "--quit-on-end", "--delay", "50"] if gui else []
        # traci prints " Retrying in 1 seconds" while SUMO opens its port: not for the console
        with contextlib.redirect_stdout(io.StringIO()):
            traci.start([binary] + self.command(seed)[1:] + extra, label=label)
        self._ls = traci.getConnection(label)

    def _subscribe(self) -> None:
        ls = self._ls
        cx, cy = self.scenario.region.center
        w, h = self.scenario.region.size
        radius = math.hypot(w, h) / 2 + 30.0
        ls.poi.add("cosim_region", cx, cy, (0, 0, 0, 0))
        ls.poi.subscribeContext(
            "cosim_region", _CMD_GET_VEHICLE_VARIABLE, radius,
            [_VAR_POSITION, _VAR_ANGLE, _VAR_SPEED, _VAR_TYPE, _VAR_LANE_ID, _VAR_LANEPOSITION],
        )
        if self.pedestrians:
            ls.poi.add("cosim_region_p", cx, cy, (0, 0, 0, 0))
            ls.poi.subscribeContext(
                "cosim_region_p", _CMD_GET_PERSON_VARIABLE, radius,
                [_VAR_POSITION, _VAR_ANGLE, _VAR_SPEED, _VAR_ROAD_ID],
            )

    def close(self) -> None:
        """Close SUMO. Safe to call twice or after a failure."""
        global _owner
        if self._running and self._ls is not None:
            self._running = False
            try:
                self._ls.close()
            except Exception as exc:  # already gone: nothing left to release
                log.debug("closing SUMO raised %s", exc)
        self._running = False
        if _owner is not None and _owner() is self:
            _owner = None

    @property
    def running(self) -> bool:
        return self._running

    def __enter__(self) -> SumoBridge:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: modules may already be gone
            pass

    def _fail(self, what: str, exc: Exception, seed: int | None = None):
        self.close()
        reason = " ".join(str(exc).split())
        if not reason and seed is not None:
            reason = self._startup_error(seed)
        raise SumoError(f"{what}: {reason or 'SUMO gave no reason (its own messages are above)'}") from exc

    def _startup_error(self, seed: int) -> str:
        """Why SUMO refused to start, from its error log (libsumo's exception is then empty).

        Starts libsumo once more with ``--error-log`` (it fails again at loading, in
        milliseconds); SUMO writes the log only when it closes. Skipped while another
        environment of this process holds libsumo.
        """
        owner = _owner() if _owner is not None else None
        if owner is not None and owner._running:
            return ""
        fd, name = tempfile.mkstemp(prefix="cosim-sumo-", suffix=".log")
        os.close(fd)
        try:
            ls = _libsumo()
            try:
                ls.start(self.command(seed) + ["--error-log", name])
            except Exception:  # the failure being diagnosed
                pass
            try:
                ls.close()
            except Exception:  # nothing was started
                pass
            lines = [ln.strip() for ln in Path(name).read_text(errors="replace").splitlines()]
            last = next((ln for ln in reversed(lines) if ln), "")
            return last.removeprefix("Error: ")
        finally:
            os.unlink(name)

    def _check(self):
        if not self._running:
            raise SumoError("the SUMO simulation is not running; call start()/reset() first")
        return self._ls

    # -- per-step ------------------------------------------------------------
    def advance(self, seconds: float) -> None:
        """Run background traffic alone for some simulated seconds (warm-up)."""
        ls = self._check()
        steps = int(round(seconds / self.scenario.dt))
        try:
            for _ in range(steps):
                ls.simulationStep()
        except self._errors as exc:
            self._fail("SUMO failed during warm-up", exc)
        self.time = ls.simulation.getTime()

    def clear_around(self, points: np.ndarray, radius: float) -> int:
        """Remove background cars within `radius` of any point (free the AC spawn spots)."""
        ls = self._check()
        res = ls.poi.getContextSubscriptionResults("cosim_region") or {}
        removed = 0
        for vid, var in res.items():
            if vid in self._acs:
                continue
            x, y = var[_VAR_POSITION]
            if np.min(np.hypot(points[:, 0] - x, points[:, 1] - y)) < radius:
                ls.vehicle.remove(vid)
                removed += 1
        return removed

    def add_ac(self, ac_id: str, edges, sumo_lane: int, pos: float, length: float, width: float,
               color=(255, 40, 40, 255)) -> None:
        """Add a learning car as a SUMO vehicle of its own vType on its route."""
        ls = self._check()
        try:
            route_id = f"{ac_id}__route"
            ls.route.add(route_id, list(edges))
            type_id = f"{ac_id}__type"
            ls.vehicletype.copy("DEFAULT_VEHTYPE", type_id)
            ls.vehicletype.setLength(type_id, length)
            ls.vehicletype.setWidth(type_id, width)
            ls.vehicletype.setColor(type_id, color)
            self._acs[ac_id] = (route_id, sumo_lane, pos)
            self._insert_ac(ac_id)
        except self._errors as exc:
            self._acs.pop(ac_id, None)
            self._fail(f"SUMO refused learning car {ac_id!r} on route {list(edges)}", exc)

    def _insert_ac(self, ac_id: str) -> None:
        """(Re-)insert an AC's SUMO vehicle on its route; we drive it, SUMO must not."""
        ls = self._ls
        route_id, lane, pos = self._acs[ac_id]
        ls.vehicle.add(ac_id, route_id, typeID=f"{ac_id}__type", depart="now",
                       departLane=str(lane), departPos=f"{pos:.2f}", departSpeed="0")
        ls.vehicle.setSpeedMode(ac_id, 0)
        ls.vehicle.setLaneChangeMode(ac_id, 0)

    def move_ac(self, ac_id: str, x: float, y: float, heading: float, length: float) -> None:
        """Place an AC (centre pose) for the next SUMO step; it may leave the road."""
        ls = self._ls
        fx = x + math.cos(heading) * length / 2
        fy = y + math.sin(heading) * length / 2
        try:
            ls.vehicle.moveToXY(ac_id, "", -1, fx, fy, heading_to_sumo(heading), 2)
        except self._errors:
            # SUMO removed it (e.g. it ran off the end of its route): put it back, then move.
            try:
                self._insert_ac(ac_id)
                ls.vehicle.moveToXY(ac_id, "", -1, fx, fy, heading_to_sumo(heading), 2)
            except self._errors as exc:
                self._fail(f"SUMO lost learning car {ac_id!r} and could not re-insert it", exc)

    def place_car(self, vid: str, x: float, y: float, heading: float, edge: str) -> None:
        """Put a standing background car at a centre pose (for tests and scripted set-ups).

        `edge` is any edge it could drive on; the car never moves by itself.
        """
        ls = self._check()
        try:
            if "cosim_parked" not in ls.vehicletype.getIDList():
                ls.vehicletype.copy("DEFAULT_VEHTYPE", "cosim_parked")
                ls.vehicletype.setLength("cosim_parked", 4.5)
                ls.vehicletype.setWidth("cosim_parked", 1.8)
            ls.route.add(f"{vid}__route", [edge])
            ls.vehicle.add(vid, f"{vid}__route", typeID="cosim_parked", depart="now", departSpeed="0")
            ls.vehicle.setSpeedMode(vid, 0)
            ls.vehicle.setSpeed(vid, 0.0)
            fx, fy = x + math.cos(heading) * 2.25, y + math.sin(heading) * 2.25
            ls.vehicle.moveToXY(vid, edge, -1, fx, fy, heading_to_sumo(heading), 2)
        except self._errors as exc:
            self._fail(f"SUMO refused to place car {vid!r}", exc)

    def place_person(self, pid: str, x: float, y: float, edge: str) -> None:
        """Pin a standing pedestrian at (x, y), e.g. on a crossing (tests, scripted set-ups).

        SUMO puts a waiting person back on its edge, so the bridge re-places pinned
        people before every step.
        """
        ls = self._check()
        try:
            ls.person.add(pid, edge, 0.0)
            ls.person.appendWaitingStage(pid, 100000.0)
            ls.person.moveToXY(pid, edge, x, y, keepRoute=2)
        except self._errors as exc:
            self._fail(f"SUMO refused to place person {pid!r}", exc)
        self._pinned[pid] = (x, y, edge)

    def remove_ac(self, ac_id: str) -> None:
        """Take a finished AC out of SUMO so it no longer blocks traffic."""
        if ac_id not in self._acs:
            return
        del self._acs[ac_id]
        try:
            self._ls.vehicle.remove(ac_id)
        except self._errors:
            pass  # not inserted (yet) or already gone: either way it is out

    def step(self) -> None:
        """Advance SUMO by one dt."""
        ls = self._check()
        try:
            for pid, (x, y, edge) in self._pinned.items():
                ls.person.moveToXY(pid, edge, x, y, keepRoute=2)
            ls.simulationStep()
            self._steps += 1
            if self._steps % GRIDLOCK_CHECK_EVERY == 0:
                self._clear_gridlock()
        except self._errors as exc:
            self._fail("SUMO failed during simulationStep", exc)
        self.time += self.scenario.dt

    def gate_entries(self, ids: list[str], corners: np.ndarray, ahead: np.ndarray | None = None,
                     moving: np.ndarray | None = None) -> None:
        """Hold background cars before a junction while an AC is on their path through it.

        An AC moved by ``moveToXY`` registers no approach to the junction's links, and SUMO
        checks a foe in the junction only at the point where the two lanes' centre lines
        cross, as if it kept its speed: a car waiting at the stop line starts once an AC's
        front has passed that point, though the AC's body may still lie across the mouth it
        enters (two left turns from neighbouring arms run within 2 m of each other there),
        and it starts while an AC that slows in the junction has still to cross.

        So before each step, a background car within GATE_REACH m of a junction that can
        still stop before it is held (speed 0) while an AC is on its path through the
        junction, and released after. "On its path" means: a corner or a centre-line point
        of an AC's body (`corners`, (n, 4, 2), of the ACs `ids`) or, for a moving AC
        (`moving`, (n,) bools, 0.5 m/s or more; all when None) inside a junction, a point of
        the rest of its own path through it, within half the car's width + GATE_MARGIN
        (+ half the AC's width for centre points) of the car's path. A standing AC holds
        only the cars its body is in the way of: one that stops with its nose in the
        junction does not stop the cross traffic for good.
        Cars already in a junction are left to SUMO (holding them there would park them in
        the AC's way). With Scenario.cars_see_acs, cars on a lane are also held for an AC
        anywhere on their lane ahead (:meth:`_cars_seeing`), and people anywhere for a
        moving AC on their next steps (:meth:`_people_seeing`).

        People get the same at zebra crossings, which SUMO lets them step onto in front of
        an AC for the same reason: one on the walking area before a crossing waits while a
        moving AC is on the crossing or will be in the next seconds (`ahead`, (n, k, 2)
        centres). docs/scenarios.md, "SUMO's cars and
        people wait for an AC".
        """
        ls = self._ls
        cars = ls.poi.getContextSubscriptionResults("cosim_region") or {}
        corners = np.asarray(corners, dtype=float).reshape(-1, 4, 2)
        if not len(corners):
            self._release(set(), set())
            return
        half_w = float(np.linalg.norm(corners[0, 1] - corners[0, 0]) / 2)
        # the bodies: corners, and the centre line (rear to front) at half the width
        rear, front = (corners[:, 2] + corners[:, 3]) / 2, (corners[:, 0] + corners[:, 1]) / 2
        axis = rear[:, None, :] + np.linspace(0.0, 1.0, 5)[None, :, None] * (front - rear)[:, None, :]
        pts, reach = [corners.reshape(-1, 2), axis.reshape(-1, 2)], [np.zeros(corners.size // 2),
                                                                     np.full(axis.size // 2, half_w)]
        body, body_reach = np.concatenate(pts), np.concatenate(reach)
        go = np.ones(len(corners), bool) if moving is None else np.asarray(moving, bool)
        for k, ac in enumerate(ids):
            lane = cars[ac][_VAR_LANE_ID] if ac in cars and ac in self._acs else ""
            if lane.startswith(":") and go[k]:  # the rest of its path through this junction
                path = self._junction_path(lane)
                at, _ = path.project(*corners[k].mean(axis=0))
                s = np.arange(at, path.length, 1.0)
                pts.append(np.column_stack([np.interp(s, path.cumlen, path.points[:, 0]),
                                            np.interp(s, path.cumlen, path.points[:, 1])]))
                reach.append(np.full(len(s), half_w))
        xy, rad = np.concatenate(pts), np.concatenate(reach)
        # cars on a lane (not yet in the junction), within reach of its end, able to stop
        near_end = [(vid, var) for vid, var in cars.items()
                    if vid not in self._acs and var[_VAR_LANE_ID]
                    and not var[_VAR_LANE_ID].startswith(":")
                    and var[_VAR_SPEED] ** 2 / (2 * GATE_DECEL) <= (to_go := self._to_go(var))
                    and to_go <= GATE_REACH]
        hold = {vid for vid, var in _near(near_end, xy)
                if self._blocked_entry(vid, var[_VAR_LANE_ID], xy, rad)}
        if self.scenario.cars_see_acs:
            hold |= self._cars_seeing(cars, ids, corners, body, body_reach)
        walkers: set[str] = set()
        if self.pedestrians:
            # a person waits for a moving AC on the crossing or driving onto it, not for one
            # standing (it may be waiting for that person: both would wait for good), nor
            # for the rest of an AC's path (it may stop before the crossing)
            later = np.zeros((len(corners), 0, 2)) if ahead is None else np.asarray(ahead, float)
            pxy = np.concatenate([corners[go].reshape(-1, 2), axis[go].reshape(-1, 2),
                                  later[go].reshape(-1, 2)])
            prad = np.concatenate([np.zeros(4 * go.sum()),
                                   np.full(len(pxy) - 4 * go.sum(), half_w)])
            people = ls.poi.getContextSubscriptionResults("cosim_region_p") or {}
            on_walking_area = [(pid, var) for pid, var in people.items()
                               if var[_VAR_ROAD_ID].startswith(":") and "_w" in var[_VAR_ROAD_ID]]
            walkers = {pid for pid, var in _near(on_walking_area, pxy)
                       if self._blocked_crossing(pid, pxy, prad)}
            if self.scenario.cars_see_acs:
                walkers |= self._people_seeing(people, corners[go])
        self._release(hold, walkers)

    def _to_go(self, var: dict) -> float:
        """Metres from a car (subscription results `var`) to the end of its lane."""
        lane = var[_VAR_LANE_ID]
        if lane not in self._lane_length:
            self._lane_length[lane] = self._ls.lane.getLength(lane)
        return self._lane_length[lane] - var[_VAR_LANEPOSITION]

    def _release(self, hold: set[str], walkers: set[str]) -> None:
        """Hold the cars in `hold` and people in `walkers`; let go of the rest held so far."""
        ls = self._ls
        for vid in hold - self._held:
            with contextlib.suppress(*self._errors):  # e.g. an AC that finished this step
                ls.vehicle.setSpeed(vid, 0.0)
        for vid in self._held - hold:
            with contextlib.suppress(*self._errors):  # it may have left the simulation
                ls.vehicle.setSpeed(vid, -1.0)  # back to SUMO's own speed
        for pid in walkers - self._held_people:
            with contextlib.suppress(*self._errors):
                ls.person.setSpeed(pid, 0.0)
        for pid in self._held_people - walkers:
            with contextlib.suppress(*self._errors):
                ls.person.setSpeed(pid, -1.0)
        self._held, self._held_people = hold, walkers

    def _blocked_crossing(self, pid: str, pts: np.ndarray, rad: np.ndarray) -> bool:
        """Whether person `pid`, on a walking area, is about to step onto a zebra crossing
        that one of `pts` (each with its radius `rad`) is on."""
        try:  # not cached: a person may cross twice from one walking area (there and back)
            crossing = self._ls.person.getNextEdge(pid)
        except self._errors:
            return False
        if not (crossing.startswith(":") and "_c" in crossing):
            return False
        if crossing not in self._half:
            lane = f"{crossing}_0"
            shape = np.asarray([p[:2] for p in self._ls.lane.getShape(lane)], dtype=float)
            self._paths[crossing] = Polyline.from_points(shape)
            self._half[crossing] = self._ls.lane.getWidth(lane) / 2
        return _touches(self._paths[crossing], pts, rad + self._half[crossing] + GATE_MARGIN)

    def _blocked_entry(self, vid: str, lane: str, pts: np.ndarray, rad: np.ndarray) -> bool:
        """Whether background car `vid`, on `lane`, enters the junction at its end on a path
        that one of `pts` (each with its radius `rad`) touches."""
        link = self._next_link(vid, lane)
        if link is None:
            return False
        return _touches(self._junction_path(link[0]), pts, rad + self._half[vid] + GATE_MARGIN)

    def _next_link(self, vid: str, lane: str) -> tuple[str, str] | None:
        """(first internal lane, lane after the junction) of background car `vid`'s way on
        from the end of `lane`; None where it enters no junction there, or it has left the
        simulation. Cached per car and lane (a car's way on from a lane does not change);
        half the car's width is cached with it (:meth:`_car_half`)."""
        key = (vid, lane)
        if key not in self._next:
            try:
                links = self._ls.vehicle.getNextLinks(vid)
            except self._errors:
                return None  # left the simulation in the last step (a finished AC, a cleared car)
            if self._car_half(vid) is None:
                return None
            # (lane after, priority, open, foe, via internal lane, state, direction, length)
            self._next[key] = (links[0][4], links[0][0]) if links and links[0][4].startswith(":") else None
        return self._next[key]

    def _cars_seeing(self, cars: dict, ids: list[str], corners: np.ndarray, pts: np.ndarray,
                     rad: np.ndarray) -> set[str]:
        """With Scenario.cars_see_acs: the background cars on a lane (not in a junction) that
        one of the ACs `ids` stands in front of, on their path ahead.

        SUMO's car-following sees only a leader on the car's own lane and the lanes after it,
        and ``moveToXY`` maps an AC standing across or between lanes, or beside the road, to
        one lane or none: the cars on the other lanes its body covers drive into it and queue
        against it, each step a contact the AC is charged for. So a car is held while a point
        of an AC's body (`pts`: the corners, then the centre lines, of `corners` (n, 4, 2),
        each with its radius `rad`) lies on its path ahead (:meth:`_on_path_ahead`), counting
        only ACs whose centre is in front of the car's front: a car is not held by an AC that
        ran into it from behind or stands beside it. Nor is a car held for an AC's points beyond
        its SUMO leader (an AC or any car) within reach: it brakes for its leader, and so for
        what lies beyond it. That leaves an AC SUMO has as the car's leader to SUMO, which
        follows it at its speed (held, the cars behind an AC driving on their lane would stop
        every step), and a car held by ``setSpeed`` brakes at most at its normal deceleration,
        not as hard as car-following would for a leader that stops short (held so for a second
        AC, a car behind an AC standing after its spawn on the Roundabout ran into it).
        """
        n = len(corners)
        owner = np.concatenate([np.repeat(np.arange(n), 4), np.repeat(np.arange(n), 5)])
        centre = corners.mean(axis=1)
        on_lane = [(vid, var) for vid, var in cars.items()
                   if vid not in self._acs and var[_VAR_LANE_ID]
                   and not var[_VAR_LANE_ID].startswith(":")
                   and var[_VAR_TYPE] != "cosim_parked"]  # place_car's: released, it would drive
        seeing: set[str] = set()
        for vid, var in _near(on_lane, pts, SEE_NEAR):
            front = np.asarray(var[_VAR_POSITION], dtype=float)
            h = float(sumo_to_heading(var[_VAR_ANGLE]))
            reach = var[_VAR_SPEED] ** 2 / (2 * GATE_DECEL) + SEE_BUFFER
            half = self._car_half(vid)
            if half is None:
                continue  # left the simulation in the last step
            side = rad + half + GATE_MARGIN
            # of ACs ahead, the points no further from its front than its path ahead reaches
            # (a path is never shorter than the straight line; 1 m for the front's projection)
            ahead = (((centre - front) @ np.array([math.cos(h), math.sin(h)]) > 0.0)[owner]
                     & (((pts - front) ** 2).sum(axis=1) < (reach + side + 1.0) ** 2))
            if not ahead.any():
                continue
            dist = self._on_path_ahead(vid, var, pts[ahead], side[ahead], reach)
            if not np.isfinite(dist).any():
                continue
            leader, gap = self._leader(vid, reach)
            # the other ACs' points on its path: SUMO brakes for its leader (an AC or any car)
            # and so for what lies beyond it: only the points nearer than it count
            other = (owner[ahead] != (ids.index(leader) if leader in ids else -1)) & (dist < gap)
            if np.isfinite(dist[other]).any():
                seeing.add(vid)
        return seeing

    def _people_seeing(self, people: dict, corners: np.ndarray) -> set[str]:
        """With Scenario.cars_see_acs: the people (subscription results `people`) that a
        moving AC's body (`corners`, (n, 4, 2), of the moving ACs only) lies in front of, on
        their next PERSON_AHEAD m of walk.

        SUMO's people do not avoid vehicles: they walk into an AC driving across a sidewalk or
        a crossing wherever it is, a contact the AC is charged for (the junction gate holds
        them only on a walking area before a crossing a moving AC is on). So a person is held
        (speed 0; released the step its way is clear) while a point of its walk straight ahead
        along its heading, PERSON_STEP m apart from its position to PERSON_AHEAD m on, lies
        inside an AC's body grown by PERSON_RADIUS + GATE_MARGIN, counting only ACs it does not
        touch already (one that ran into it: held, it would stand in the contact). Not for a
        standing AC, as the gate: one that walks into a standing AC is not its collision
        (cosim/events.py), and a standing AC may be waiting for that very person (held for
        standing ACs too, two autopilot ACs and two people waited for each other for the last
        400 of 600 steps on Three-way, seed 10,000). Pinned people (:meth:`place_person`) are
        left alone.
        """
        if not len(corners) or not people:
            return set()
        front, rear = (corners[:, 0] + corners[:, 1]) / 2, (corners[:, 2] + corners[:, 3]) / 2
        centre, axis = (front + rear) / 2, front - rear
        half_l = np.linalg.norm(axis, axis=1) / 2
        u = axis / np.maximum(2 * half_l, 1e-9)[:, None]  # (n, 2) unit heading of each AC
        v = np.stack([-u[:, 1], u[:, 0]], axis=1)
        half_w = np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1) / 2
        grow = PERSON_RADIUS + GATE_MARGIN
        radius = PERSON_AHEAD + grow + float(np.hypot(half_l, half_w).max())
        near = [(pid, var) for pid, var in _near(list(people.items()), centre, radius)
                if pid not in self._pinned]
        if not near:
            return set()
        at = np.array([var[_VAR_POSITION] for _, var in near], dtype=float)  # (m, 2)
        h = sumo_to_heading(np.array([var[_VAR_ANGLE] for _, var in near], dtype=float))
        d = np.arange(0.0, PERSON_AHEAD + 1e-9, PERSON_STEP)  # (k,)
        walk = at[:, None, :] + d[None, :, None] * np.stack([np.cos(h), np.sin(h)], axis=1)[:, None, :]
        rel = walk[:, :, None, :] - centre[None, None, :, :]  # (m, k, n, 2)
        lon = np.abs((rel * u[None, None]).sum(axis=3))
        lat = np.abs((rel * v[None, None]).sum(axis=3))
        inside = (lon <= half_l + grow) & (lat <= half_w + grow)  # (m, k, n)
        touching = (lon[:, 0] <= half_l + PERSON_RADIUS) & (lat[:, 0] <= half_w + PERSON_RADIUS)
        hold = (inside[:, 1:].any(axis=1) & ~touching).any(axis=1)
        return {pid for (pid, _), held in zip(near, hold, strict=True) if held}

    def _on_path_ahead(self, vid: str, var: dict, pts: np.ndarray, side: np.ndarray,
                       reach: float) -> np.ndarray:
        """How far ahead of background car `vid`'s front (subscription results `var`) each of
        `pts` lies on its path, inf where it is not on it: within `side` m (each point's: half
        the car's width + GATE_MARGIN + its radius) of the centre line of its lane, from its
        front to `reach` m on; where the lane ends sooner, on along its path through the next
        junction (its internal lanes) and into the lane after it, no further."""
        lane = var[_VAR_LANE_ID]
        path = self._lane_path(lane)
        start, _ = path.project(*var[_VAR_POSITION])  # its front
        dist = _along_beside(path, pts, side, start, start + reach) - start
        left = reach - (path.length - start)
        link = self._next_link(vid, lane) if left > 0 else None
        if link is not None:
            through, before = self._junction_path(link[0]), path.length - start
            dist = np.minimum(dist, _along_beside(through, pts, side, 0.0, left) + before)
            if left > through.length:
                after = self._lane_path(link[1])
                dist = np.minimum(dist, _along_beside(after, pts, side, 0.0, left - through.length)
                                  + before + through.length)
        return dist

    def _car_half(self, vid: str) -> float | None:
        """Half the width of car `vid` (cached, with its minGap for :meth:`_leader`), None when
        it has left the simulation."""
        if vid not in self._half:
            try:
                half, gap = self._ls.vehicle.getWidth(vid) / 2, self._ls.vehicle.getMinGap(vid)
            except self._errors:
                return None
            self._half[vid], self._min_gap[vid] = half, gap
        return self._half[vid]

    def _lane_path(self, lane: str) -> Polyline:
        """The centre line of a (normal) lane, cached."""
        if lane not in self._lanes:
            shape = [p[:2] for p in self._ls.lane.getShape(lane)]
            self._lanes[lane] = Polyline.from_points(np.asarray(shape, dtype=float))
        return self._lanes[lane]

    def _leader(self, vid: str, dist: float) -> tuple[str, float]:
        """(id, metres from car `vid`'s front to its rear) of the vehicle SUMO has as the
        car's leader within `dist` m; ("", inf) for none. `vid` has been through
        :meth:`_car_half` (its minGap is cached there)."""
        try:
            lead = self._ls.vehicle.getLeader(vid, dist)
        except self._errors:
            return "", math.inf
        if not lead or not lead[0]:  # libsumo: ("", -1) for none; TraCI: None
            return "", math.inf
        return lead[0], lead[1] + self._min_gap[vid]

    def _junction_path(self, internal: str) -> Polyline:
        """The centre line through the junction from `internal` on (its internal lanes)."""
        if internal not in self._paths:
            ls, shape, lane = self._ls, [], internal
            while lane.startswith(":") and len(shape) < 200:
                pts = [p[:2] for p in ls.lane.getShape(lane)]
                shape += pts if not shape else pts[1:]
                nxt = ls.lane.getLinks(lane)  # (lane, prio, open, foe, via internal lane, ...)
                lane = (nxt[0][4] if nxt[0][4].startswith(":") else nxt[0][0]) if nxt else ""
            self._paths[internal] = Polyline.from_points(np.asarray(shape, dtype=float))
        return self._paths[internal]

    def _clear_gridlock(self) -> None:
        """Remove background cars that have stood inside a junction for GRIDLOCK_WAIT s.

        SUMO's own gridlock breaker (--time-to-teleport) is off because it would teleport
        the ACs, whose poses we set; SUMO's cars and pedestrians yield to an AC standing
        in a junction while it waits for them, so without this a junction can lock for good.
        """
        ls = self._ls
        cars = ls.poi.getContextSubscriptionResults("cosim_region") or {}
        for vid, var in cars.items():
            if vid in self._acs or var[_VAR_SPEED] > 0.1:
                continue
            if (ls.vehicle.getRoadID(vid).startswith(":")
                    and ls.vehicle.getWaitingTime(vid) > GRIDLOCK_WAIT):
                ls.vehicle.remove(vid)

    def background_actors(self) -> tuple:
        """(car ids, centres, headings, speeds, lengths, widths, person ids, xy, headings, speeds)."""
        ls = self._ls
        cars = ls.poi.getContextSubscriptionResults("cosim_region") or {}
        ids, xy, hd, sp, ln, wd = [], [], [], [], [], []
        for vid, var in cars.items():
            if vid in self._acs:
                continue
            vtype = var[_VAR_TYPE]
            size = self._type_size.get(vtype)
            if size is None:
                size = (ls.vehicletype.getLength(vtype), ls.vehicletype.getWidth(vtype))
                self._type_size[vtype] = size
            ids.append(vid)
            xy.append(var[_VAR_POSITION])
            hd.append(var[_VAR_ANGLE])
            sp.append(var[_VAR_SPEED])
            ln.append(size[0])
            wd.append(size[1])
        xy_a = np.asarray(xy, dtype=float).reshape(-1, 2)
        heading = sumo_to_heading(np.asarray(hd, dtype=float))
        length = np.asarray(ln, dtype=float)
        # front bumper -> centre
        xy_a = xy_a - np.stack([np.cos(heading), np.sin(heading)], axis=1) * (length[:, None] / 2)
        persons = (
            ls.poi.getContextSubscriptionResults("cosim_region_p") or {} if self.pedestrians else {}
        )
        pids = list(persons)
        pxy = np.asarray([persons[p][_VAR_POSITION] for p in pids], dtype=float).reshape(-1, 2)
        phd = sumo_to_heading(np.asarray([persons[p][_VAR_ANGLE] for p in pids], dtype=float))
        psp = np.asarray([persons[p][_VAR_SPEED] for p in pids], dtype=float)
        return (ids, xy_a, heading, np.asarray(sp, dtype=float), length, np.asarray(wd, dtype=float),
                pids, pxy, phd, psp)

    def signal_states(self, tls_ids) -> dict[str, str]:
        """SUMO's red/yellow/green state string of each traffic light in `tls_ids`."""
        ls = self._check()
        try:
            return {t: ls.trafficlight.getRedYellowGreenState(t) for t in tls_ids}
        except self._errors as exc:
            self._fail("SUMO could not read the traffic light states", exc)

    def next_tls(self, ac_id: str) -> tuple[str, float] | None:
        """(state char, distance m) of the next traffic light on the AC's route, if any."""
        try:
            nxt = self._ls.vehicle.getNextTLS(ac_id)
        except self._errors:
            return None
        if not nxt:
            return None
        _tls, _index, dist, state = nxt[0]
        return state, float(dist)
