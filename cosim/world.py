"""The world without cameras: SUMO traffic + ego dynamics + events + reward.

:class:`World` owns one SUMO simulation and the state of N learning cars (ACs).
The environments (:mod:`cosim.env`) add the PyBullet mirror and the cameras on
top of it; benchmarks and the scripted controller use it directly.

The order of one step (docs/guide.md#the-order-of-one-step), done in :meth:`World.step`:

1. actions -> controls (throttle/brake, steer), validated per AC
2. ego dynamics: kinematic bicycle over dt, for every active AC
3. SUMO: each AC's pose pushed with moveToXY(keepRoute=2)
4. SUMO: simulationStep(); background cars and pedestrians react
5. SUMO: snapshot of every actor through the context subscriptions
6. events: collisions (vehicle / pedestrian / object), off-road, wrong lane, goal
7. reward: named terms + weighted sum
   (before the reward: each contact with another actor is a collision event once per
   Contact.window; static road objects, and with Scenario.solid_cars (the default) a car
   ahead that the move drove into, are solid: the AC is put back BACK_OFF behind where it was
   before the step, standing, and that step credits no progress; docs/task.md, "Collision rule")
8. termination / truncation; finished ACs leave SUMO
(the env then syncs the PyBullet mirror to the snapshot and renders one camera per AC)
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from cosim.dynamics import VehicleParams, bicycle_step
from cosim.errors import EnvStateError, ScenarioError
from cosim.events import PEDESTRIAN_MIN_SPEED, Events, detect_all, reward_terms
from cosim.geometry import convex_overlap, rect_corners, rect_corners_many
from cosim.roadmap import RoadMap, road_map
from cosim.scenario import Scenario, load_scenario
from cosim.score import RouteCompletion
from cosim.sumo_bridge import GATE_AHEAD, Snapshot, SumoBridge

log = logging.getLogger(__name__)

SPAWN_CLEARANCE = 12.0  # metres around each spawn point cleared of background cars
BACK_OFF = 1.0
"""Metres a blocked AC is put back behind its pose before the step (where that spot is clear):
room to steer away from what stopped it, which a car put back exactly where it was, standing,
with no reverse, never gets (docs/task.md, "Collision rule")."""
NEW_GROUND_EPS = 1e-6
"""Metres: a step reaches new ground when it leaves the AC nearer its goal than it has been, by
more than this; only such steps earn the speed term F (Events.new_ground; docs/task.md,
"Collision rule": a car bouncing off what it drove into re-drives the metre it was put back)."""
STALL_SPEED = 0.1
"""m/s: an AC slower than this stands (Termination.stall_truncate)."""
STALL_SIGNAL_M = 30.0
"""Metres: an AC standing this near a red or yellow signal ahead waits for it, not stalls."""
AC_COLORS = (
    (230, 40, 40, 255), (250, 140, 20, 255), (200, 40, 200, 255),
    (40, 200, 60, 255), (240, 220, 30, 255), (30, 200, 220, 255),
)


@dataclass
class ACResult:
    """One AC's outcome of a step."""

    events: Events
    reward_terms: dict[str, float]
    reward: float
    terminated: bool
    truncated: bool
    x: float
    y: float
    heading: float

    def info(self) -> dict:
        d = self.events.as_dict()
        d.update(x=self.x, y=self.y, heading=self.heading, reward_terms=dict(self.reward_terms))
        return d


@dataclass
class StepTimes:
    """Wall seconds spent in each phase, accumulated since the last reset."""

    dynamics: float = 0.0
    sumo: float = 0.0
    snapshot: float = 0.0
    events: float = 0.0
    steps: int = 0


class World:
    """SUMO + N ACs of one scenario. See the module docstring for the step order."""

    def __init__(
        self,
        scenario: Scenario | str,
        num_acs: int | None = None,
        *,
        background: bool = True,
        pedestrians: bool = True,
        vehicle: VehicleParams | None = None,
        backend: str = "auto",
    ):
        self.scenario = load_scenario(scenario) if isinstance(scenario, str) else scenario
        if vehicle is not None:  # one car everywhere: road map, cameras and dynamics read it
            self.scenario = self.scenario.with_overrides(vehicle=vehicle)
        n = self.scenario.max_agents if num_acs is None else int(num_acs)
        if not 1 <= n <= self.scenario.max_agents:
            raise ScenarioError(
                f"scenario {self.scenario.name!r} has spawn points for 1..{self.scenario.max_agents} "
                f"learning cars, asked for {num_acs}"
            )
        self.num_acs = n
        self.ac_ids = [f"ac_{i}" for i in range(n)]
        self.index = {ac: i for i, ac in enumerate(self.ac_ids)}
        """AC id -> its row in the state arrays (and its priority: lower goes first)."""
        self.vehicle: VehicleParams = self.scenario.vehicle
        """The ACs' car: the scenario's ``vehicle`` (its YAML's ``vehicle:`` block), or ``vehicle``."""
        self.roadmap: RoadMap = road_map(self.scenario)
        self.routes = self.roadmap.routes[:n]
        self.bridge = SumoBridge(
            self.scenario, background=background, pedestrians=pedestrians, backend=backend
        )
        self.signal_ids = sorted({tls for r in self.routes for _, tls, _ in r.signals})
        self.times = StepTimes()
        self.snapshot: Snapshot | None = None
        self.active: list[str] = []
        self.step_count = 0
        self._state = np.zeros((n, 4))  # x, y, heading, speed
        self._distance = np.zeros(n)
        self._best = np.zeros(n)  # the least distance to the goal each AC has reached (new ground)
        self._started = False

    # -- lifecycle -----------------------------------------------------------
    def reset(self, seed: int = 0) -> dict[str, ACResult]:
        """Restart SUMO with `seed`, warm up the traffic, place the ACs at their spawn poses."""
        self.bridge.start(seed)
        self._started = True
        self.bridge.advance(self.scenario.warmup)
        spawns = np.array([r.spawn_xy for r in self.routes])
        self.bridge.clear_around(spawns, SPAWN_CLEARANCE)
        jitter = self.scenario.spawn_jitter
        rng = np.random.default_rng([seed % 2**32, 1])  # its own stream: SUMO keeps the seed itself
        offsets = rng.uniform(-1.0, 1.0, (self.num_acs, 2)) * [math.radians(jitter.heading_deg), jitter.lateral]
        for i, (ac, route) in enumerate(zip(self.ac_ids, self.routes, strict=True)):
            x, y = route.spawn_xy
            h = route.spawn_heading
            x, y = x - math.sin(h) * offsets[i, 1], y + math.cos(h) * offsets[i, 1]  # + = to the left
            self._state[i] = (x, y, h + offsets[i, 0], self.scenario.acs[i].depart_speed)
            self._distance[i] = route.goal_s - route.spawn_s
            self.bridge.add_ac(
                ac, route.edges, route.sumo_lane, route.spawn_s, self.vehicle.length,
                self.vehicle.width, AC_COLORS[i % len(AC_COLORS)],
            )
        self.active = list(self.ac_ids)
        self.step_count = 0
        self._events_seen: list[dict[tuple[str, str], float]] = [{} for _ in self.ac_ids]
        """Per AC: (kind, actor id) -> simulated time of its last collision event (the test's count)."""
        self._charged: list[dict[str, float]] = [{} for _ in self.ac_ids]
        """Per AC: vehicle id -> simulated time of its last vehicle event charged at fault."""
        self._completion = [RouteCompletion(max(r.goal_s - r.spawn_s, 1e-6)) for r in self.routes]
        self._still = np.zeros(self.num_acs, dtype=int)  # consecutive standing steps (_stalled)
        self.times = StepTimes()
        # one SUMO step so the ACs are inserted and every actor has a pose
        for i, ac in enumerate(self.ac_ids):
            x, y, h, _ = self._state[i]
            self.bridge.move_ac(ac, x, y, h, self.vehicle.length)
        self.bridge.step()
        self.snapshot = self._make_snapshot()
        return self._results(np.arange(self.num_acs), initial=True)

    def close(self) -> None:
        """Close SUMO (idempotent)."""
        self.bridge.close()
        self._started = False

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- stepping ------------------------------------------------------------
    def step(self, controls: dict[str, tuple[float, float]]) -> dict[str, ACResult]:
        """Advance one dt. `controls` maps each active AC to (throttle/brake, steer) in [-1, 1].

        Returns a result for every AC that was active at the start of the step;
        the ones that terminated or were truncated are no longer active after it.
        """
        if not self._started or self.snapshot is None:
            raise EnvStateError("World.step() called before reset()")
        if not self.active:
            raise EnvStateError("every learning car is done; call reset() to start a new episode")
        t0 = time.perf_counter()
        idx = np.array([self.index[a] for a in self.active])
        tb = np.array([controls[a][0] for a in self.active], dtype=float)
        steer = np.array([controls[a][1] for a in self.active], dtype=float)
        s = self._state[idx]  # a copy (fancy indexing): the pose before the step
        # 2. ego dynamics
        nx, ny, nh, nv = bicycle_step(
            s[:, 0], s[:, 1], s[:, 2], s[:, 3], tb, steer, self.vehicle, self.scenario.dt
        )
        self._state[idx] = np.stack([nx, ny, nh, nv], axis=1)
        # 3. poses to SUMO
        for k, i in enumerate(idx):
            self.bridge.move_ac(self.ac_ids[i], nx[k], ny[k], nh[k], self.vehicle.length)
        corners = rect_corners_many(np.stack([nx, ny], axis=1), nh, self.vehicle.length,
                                    self.vehicle.width)
        ahead = np.asarray(GATE_AHEAD)[None, :] * np.maximum(nv, 0.0)[:, None]  # (n, T) metres
        ahead_xy = np.stack([nx[:, None] + np.cos(nh)[:, None] * ahead,
                             ny[:, None] + np.sin(nh)[:, None] * ahead], axis=2)
        self.bridge.gate_entries([self.ac_ids[i] for i in idx], corners, ahead_xy,
                                 nv >= PEDESTRIAN_MIN_SPEED)
        t1 = time.perf_counter()
        # 4. SUMO step
        self.bridge.step()
        t2 = time.perf_counter()
        # 5. snapshot
        self.snapshot = self._make_snapshot()
        t3 = time.perf_counter()
        # 6-8. events, reward, termination
        self.step_count += 1
        results = self._results(idx, stalled=self._stalled(idx, nv), before=s)
        for ac, res in results.items():
            if res.terminated or res.truncated:
                self.active.remove(ac)
                self.bridge.remove_ac(ac)
        t4 = time.perf_counter()
        tm = self.times
        tm.dynamics += t1 - t0
        tm.sumo += t2 - t1
        tm.snapshot += t3 - t2
        tm.events += t4 - t3
        tm.steps += 1
        return results

    def _ahead(self, i: int, vehicle: str) -> int | None:
        """The snapshot row of `vehicle` when its centre lies in front of AC `i`'s (after its
        move), else None: the AC drove into it, or it into the AC's side or front."""
        snap = self.snapshot
        try:
            j = snap.vehicle_ids.index(vehicle)
        except ValueError:
            return None
        x, y, h, _ = self._state[i]
        dx, dy = snap.vehicle_xy[j] - (x, y)
        return j if dx * math.cos(h) + dy * math.sin(h) > 0.0 else None

    def _count_events(self, i: int, ev: Events) -> None:
        """Mark the collision events that start this step: ``ev.event_*``, the events the test
        scores (every actor in contact is a new event unless that actor's last event with this
        AC is less than Contact.window seconds old, whoever caused it), and
        ``ev.charged_vehicle``, a vehicle event the reward charges this AC. With Contact.fault
        "at_fault" (the default since task version 5) a vehicle contact is charged only when
        this AC drove into the other (moving, the other's centre ahead), with its own window;
        with "both" every vehicle event is charged."""
        contact = self.scenario.contact
        now = float(self.snapshot.time)
        memory, charged = self._events_seen[i], self._charged[i]
        for kind, other in ev.touching:
            last = memory.get((kind, other))
            if last is None or now - last >= contact.window - 1e-9:
                memory[(kind, other)] = now
                setattr(ev, f"event_{kind}", True)
                if kind == "vehicle" and contact.fault == "both":
                    ev.charged_vehicle = True
            if kind == "vehicle" and contact.fault == "at_fault" and (
                self._state[i, 3] >= PEDESTRIAN_MIN_SPEED and self._ahead(i, other) is not None
            ):
                last = charged.get(other)
                if last is None or now - last >= contact.window - 1e-9:
                    charged[other] = now
                    ev.charged_vehicle = True

    def _backed_off(self, i: int, before: np.ndarray) -> tuple[float, float, float]:
        """AC `i`'s pose BACK_OFF metres behind `before` (x, y, heading, ...) along its heading
        when its footprint there touches no road object and no other vehicle, else `before`."""
        x, y, h = (float(v) for v in before[:3])
        bx, by = x - BACK_OFF * math.cos(h), y - BACK_OFF * math.sin(h)
        mine = rect_corners(bx, by, h, self.vehicle.length, self.vehicle.width)
        reach = 0.5 * float(np.hypot(self.vehicle.length, self.vehicle.width))
        for _, k in self.roadmap.objects_near_many(np.array([[bx, by]]), reach):
            if convex_overlap(mine, self.roadmap.objects[k].polygon):
                return x, y, h
        snap = self.snapshot
        if len(snap.vehicle_xy):
            near = np.hypot(snap.vehicle_xy[:, 0] - bx, snap.vehicle_xy[:, 1] - by) <= 2 * reach + 1.0
            for j in np.flatnonzero(near):
                if snap.vehicle_ids[j] == self.ac_ids[i]:
                    continue
                theirs = rect_corners(snap.vehicle_xy[j, 0], snap.vehicle_xy[j, 1], snap.vehicle_heading[j],
                                      snap.vehicle_length[j], snap.vehicle_width[j])
                if convex_overlap(mine, theirs):
                    return x, y, h
        return bx, by, h

    def _blocked(self, i: int, ev: Events, before: np.ndarray) -> bool:
        """Whether AC `i`'s move is undone: it touches a static road object or a pedestrian
        (counted only while the AC moves), or (with Scenario.solid_cars) a vehicle ahead of it
        that its pose before the move did not touch (so an AC that another car drove into can
        still move out of the contact)."""
        if ev.collision_object or ev.collision_pedestrian:
            return True
        if not (self.scenario.solid_cars and ev.collision_vehicle):
            return False
        snap = self.snapshot
        mine = rect_corners(before[0], before[1], before[2], self.vehicle.length, self.vehicle.width)
        for kind, other in ev.touching:
            j = self._ahead(i, other) if kind == "vehicle" else None
            if j is None:
                continue
            theirs = rect_corners(snap.vehicle_xy[j, 0], snap.vehicle_xy[j, 1],
                                  snap.vehicle_heading[j], snap.vehicle_length[j],
                                  snap.vehicle_width[j])
            if not convex_overlap(mine, theirs):
                return True
        return False

    def _stalled(self, idx: np.ndarray, speed: np.ndarray) -> bool:
        """Termination.stall_truncate: count each active AC's consecutive steps standing (below
        STALL_SPEED, not waiting at a red or yellow signal within STALL_SIGNAL_M ahead); True once
        every active AC has stood that many. Always False when the option is off (0)."""
        need = self.scenario.termination.stall_truncate
        if not need:
            return False
        for k, i in enumerate(idx):
            standing = speed[k] < STALL_SPEED and not self._waits_at_signal(self.ac_ids[i])
            self._still[i] = self._still[i] + 1 if standing else 0
        return bool(np.all(self._still[idx] >= need))

    def _waits_at_signal(self, ac: str) -> bool:
        tls = self.bridge.next_tls(ac)
        return tls is not None and tls[0] in "rRyYu" and tls[1] <= STALL_SIGNAL_M

    def _make_snapshot(self) -> Snapshot:
        ids, xy, hd, sp, ln, wd, pids, pxy, phd, psp = self.bridge.background_actors()
        active = [self.index[a] for a in self.active]
        n = len(active)
        st = self._state[active]
        return Snapshot(
            time=self.bridge.time,
            vehicle_ids=ids + [self.ac_ids[i] for i in active],
            vehicle_xy=np.concatenate([xy, st[:, :2]]) if n else xy,
            vehicle_heading=np.concatenate([hd, st[:, 2]]),
            vehicle_speed=np.concatenate([sp, st[:, 3]]),
            vehicle_length=np.concatenate([ln, np.full(n, self.vehicle.length)]),
            vehicle_width=np.concatenate([wd, np.full(n, self.vehicle.width)]),
            vehicle_is_ac=np.concatenate([np.zeros(len(ids), bool), np.ones(n, bool)]),
            person_ids=pids,
            person_xy=pxy,
            person_heading=phd,
            person_speed=psp,
            signals=self.bridge.signal_states(self.signal_ids) if self.signal_ids else {},
        )

    def _results(self, idx: np.ndarray, initial: bool = False, stalled: bool = False,
                 before: np.ndarray | None = None) -> dict[str, ACResult]:
        """Events, reward and termination of the ACs `idx` at their poses after the move;
        `before` (rows of (x, y, heading, speed) before it) lets a blocked move be undone."""
        sc = self.scenario
        events = detect_all(
            [self.ac_ids[i] for i in idx], self._state[idx], self.vehicle.length,
            self.vehicle.width, self.snapshot, self.roadmap, [self.routes[i] for i in idx],
            self._distance[idx], sc.termination.goal_radius,
        )
        term = sc.termination
        out = {}
        for k, (i, ev) in enumerate(zip(idx, events, strict=True)):
            if initial:
                ev.progress = 0.0
            else:
                self._count_events(i, ev)
                if before is not None and self._blocked(i, ev, before[k]):
                    # solid: the car stops BACK_OFF behind where it was before the step, which
                    # gains nothing this step (the metre lost is progress to drive again)
                    self._state[i] = (*self._backed_off(i, before[k]), 0.0)
                    ev.progress = ev.route_speed = ev.speed = 0.0
                    ev.distance_to_goal = float(self._distance[i])
                    ev.goal_reached = ev.red_light = False
            self._distance[i] = ev.distance_to_goal
            if initial:
                self._best[i] = ev.distance_to_goal
            elif ev.distance_to_goal < self._best[i] - NEW_GROUND_EPS:
                self._best[i] = ev.distance_to_goal
            else:  # road it has driven before (after a back-off), or none: no speed credit
                ev.new_ground = False
            ev.route_completion = self._completion[i].update(ev.progress, ev.goal_reached)
            terms = reward_terms(ev, sc.reward, sc.speed_limit, per_step=sc.contact.charge == "step")
            terminated = not initial and bool(
                (term.on_collision and ev.collision)
                or (term.on_goal and ev.goal_reached)
                or (term.on_offroad and ev.off_road)
                or (term.out_of_region and ev.out_of_region)
            )
            truncated = not terminated and (self.step_count >= sc.horizon or stalled)
            x, y, h, _ = self._state[i]
            out[self.ac_ids[i]] = ACResult(
                ev, terms, float(sum(terms.values())), terminated, truncated,
                float(x), float(y), float(h),
            )
        return out

    def place_ac(self, ac: str, x: float, y: float, heading: float, speed: float = 0.0) -> None:
        """Teleport an AC to a pose (scripted set-ups and tests); takes effect next step."""
        i = self.index[ac]
        self._state[i] = (x, y, heading, speed)
        s, _ = self.routes[i].path.project(x, y)
        self._distance[i] = max(self.routes[i].goal_s - s, 0.0)
        self._best[i] = self._distance[i]

    # -- views for controllers and the mirror ---------------------------------
    def ac_state(self, ac: str) -> tuple[float, float, float, float]:
        """(x, y, heading, speed) of an AC."""
        return tuple(float(v) for v in self._state[self.index[ac]])

    def route(self, ac: str):
        return self.routes[self.index[ac]]

    def next_tls(self, ac: str):
        return self.bridge.next_tls(ac)
