"""A scripted lane-following driver, usable as an AC policy (the `autopilot` reference).

It follows its route's lane centre with pure pursuit at a target speed and
brakes for what is ahead on its path (cars, pedestrians), for red and yellow
lights, and for cars whose predicted paths cross its own in the next seconds.
It reads the world directly (privileged), so it is a reference driver, not a
learning agent.

Three references come from it (docs/task.md, "Reference policies"):
:meth:`Autopilot.act` (continuous), :meth:`Autopilot.act_discrete` (the same driver
restricted to Discrete(9), the ceiling of a discrete learner) and :class:`NonTurner`
(the same driver that never turns: it holds before the first junction its route turns at).
"""

from __future__ import annotations

import math

import numpy as np

from cosim.dynamics import discrete_controls
from cosim.geometry import Polyline, rect_corners
from cosim.roadmap import movement
from cosim.sumo_bridge import PERSON_RADIUS
from cosim.world import World

COMFORT_DECEL = 3.0  # m/s^2 used to plan stops
STOP_MARGIN = 2.5  # metres kept to what it stops behind
LATERAL_ACCEL = 2.0  # m/s^2 allowed in curves
WAIT_BEFORE_CREEP = 80  # steps stopped (not at a red light) before it creeps past crossing cars
CREEP_STEPS = 40  # steps a creep lasts once started, moving or not
CREEP_MARGIN = 0.1  # metres of lateral clearance it accepts while creeping (0.5 otherwise)
CREEP_SPEED = 1.5  # m/s at most while creeping
JUNCTION_SPAN = 20.0  # metres: crossings closer than this along a path belong to one junction
JUNCTION_LOOKAHEAD = 6.0  # seconds of walking a junction's crossings must stay clear to enter
STANDING_MARGIN = 0.2  # metres of clearance to pass a car standing across or against us
# Discrete(9) quantiser (Autopilot.act_discrete): weights of the (throttle/brake, steer)
# errors it trades off, and the most error it carries over between steps (anti-windup)
QUANT_WEIGHTS = np.array([1.0, 2.0])
QUANT_CARRY = np.array([0.5, 1.0])
HOLD_MARGIN = 2.0  # metres before the stop line it aims its front bumper at (it overshoots ~1.5 m)


def _crossing_spans(world: World, path) -> list[tuple[float, float]]:
    """(start, end) arc lengths where the path runs over a zebra crossing."""
    crossings = world.roadmap.crossings
    if not crossings:
        return []
    s = np.arange(0.0, path.length, 0.5)
    pts = np.array([path.point_at(t) for t in s])
    on = np.zeros(len(s), dtype=bool)
    for c in crossings:
        seg = Polyline.from_points(np.asarray(c.shape)[:, :2])
        _, lat = seg.project_many(pts)
        along, _ = seg.project_many(pts)
        on |= (np.abs(lat) <= c.width / 2) & (along > 0.0) & (along < seg.length)
    spans, start = [], None
    for t, flag in zip(s, on, strict=True):
        if flag and start is None:
            start = t
        elif not flag and start is not None:
            spans.append((float(start), float(t)))
            start = None
    if start is not None:
        spans.append((float(start), float(path.length)))
    # the entry and exit crossings of one junction make one span: waiting between them
    # leaves the car's side on the kerb's corner, where the people of both crossings walk
    merged: list[tuple[float, float]] = []
    for c0, c1 in spans:
        if merged and c0 - merged[-1][1] < JUNCTION_SPAN:
            merged[-1] = (merged[-1][0], c1)
        else:
            merged.append((c0, c1))
    return merged


class Autopilot:
    """Drive one AC of a :class:`World` along its route."""

    def __init__(self, world: World, ac: str, target_speed: float | None = None,
                 horizon: float = 3.0):
        self.world = world
        self.ac = ac
        self.target_speed = target_speed or world.scenario.speed_limit * 0.9
        self.horizon = horizon
        self._waited = 0
        self._creep = 0  # steps of creeping left (a gridlock breaker, see _respects)
        self._conflicts: dict[str, tuple[float, float] | None] = {}
        self._crossings = _crossing_spans(world, world.route(ac).path)
        self._carry = np.zeros(2)  # act_discrete's quantisation error, carried to the next step

    def act(self) -> np.ndarray:
        """Continuous action (throttle(+)/brake(-), steer) for the AC's current state."""
        w = self.world
        x, y, heading, v = w.ac_state(self.ac)
        route = w.route(self.ac)
        path = route.path
        s, _ = path.project(x, y)
        steer = self._steer(x, y, heading, v, path, s)
        v_target = min(self.target_speed, self._curve_speed(path, s))
        for gap in self._stops(x, y, heading, v, path, s):
            gap = self._off_crossings(s, gap)
            v_target = min(v_target, math.sqrt(2 * COMFORT_DECEL * max(gap - STOP_MARGIN, 0.0)))
        tls = w.next_tls(self.ac)
        at_red = tls is not None and tls[0] in "rRyYu" and tls[1] < 15.0
        if self._creep > 0:
            v_target = min(v_target, CREEP_SPEED)
            # a creep runs its course even once the car moves: stopping it at the first
            # metre (as a speed-based reset would) leaves every gridlock in place
            self._creep -= 1
        else:
            self._waited = self._waited + 1 if (v < 0.2 and not at_red) else 0
            if self._waited > WAIT_BEFORE_CREEP:
                self._creep, self._waited = CREEP_STEPS, 0
        a = 1.5 * (v_target - v)
        if v_target < 0.3 and v < 1.0:
            tb = -1.0
        elif a >= 0:
            tb = min(a / w.vehicle.max_accel, 1.0)
        else:
            tb = max(a / w.vehicle.max_brake, -1.0)
        return np.array([tb, steer], dtype=np.float32)

    def act_discrete(self) -> int:
        """:meth:`act` restricted to Discrete(9): the discrete action whose effect is nearest
        to the continuous one plus the error carried from earlier steps (error diffusion, a
        sigma-delta quantiser), so that over a few steps the table's few wheel angles and
        throttle levels average to the continuous autopilot's (a pulsed "left" between 35
        and 3.5 degrees makes a 20 degree curve). Effects are compared as the wheel angle
        the bicycle would really use at this speed (grip-limited, ``VehicleParams.wheel_angle``)
        and the throttle/brake level; the carry is clipped (QUANT_CARRY), so a wish the table
        cannot meet (brake harder than -0.5) does not pile up."""
        want = self.act().astype(float)
        p = self.world.vehicle
        v = self.world.ac_state(self.ac)[3]
        table = discrete_controls(p)
        have = np.column_stack([table[:, 0], p.wheel_angle(table[:, 1], v) / p.max_steer])
        target = np.array([want[0], p.wheel_angle(want[1], v) / p.max_steer]) + self._carry
        k = int(np.argmin(np.sum(((have - target) * QUANT_WEIGHTS) ** 2, axis=1)))
        self._carry = np.clip(target - have[k], -QUANT_CARRY, QUANT_CARRY)
        return k

    # -- pieces --------------------------------------------------------------
    def _off_crossings(self, s: float, gap: float) -> float:
        """Never wait on a zebra crossing, nor between a junction's entry and exit crossings:
        SUMO's pedestrians walk into a car standing there. Such a stop moves back to before
        the first crossing."""
        half = self.world.vehicle.length / 2
        stop = s + gap - STOP_MARGIN  # where the centre comes to rest
        for c0, c1 in self._crossings:
            if c0 - half < stop < c1 + half and s < c0 - half:
                return min(gap, c0 - half - 0.5 - s + STOP_MARGIN)
        return gap

    def _steer(self, x, y, heading, v, path, s) -> float:
        """Pure pursuit from the rear axle, which tracks arcs of the path exactly."""
        wb = self.world.vehicle.wheelbase
        rx, ry = x - math.cos(heading) * wb / 2, y - math.sin(heading) * wb / 2
        s_rear, _ = path.project(rx, ry)
        lookahead = max(3.5, 0.4 * v + 2.0)
        tx, ty = path.point_at(s_rear + lookahead)
        dx, dy = tx - rx, ty - ry
        # target in the car's frame; +ly is to the left
        lx = math.cos(heading) * dx + math.sin(heading) * dy
        ly = -math.sin(heading) * dx + math.cos(heading) * dy
        dist2 = max(lx * lx + ly * ly, 1e-6)
        delta = math.atan(2.0 * wb * ly / dist2)
        return float(np.clip(-delta / self.world.vehicle.max_steer, -1.0, 1.0))

    def _curve_speed(self, path, s) -> float:
        h0 = path.heading_at(s)
        worst = 0.0
        for ahead in (5.0, 10.0, 15.0, 20.0):
            dh = abs((path.heading_at(s + ahead) - h0 + math.pi) % (2 * math.pi) - math.pi)
            worst = max(worst, dh / ahead)
        return math.sqrt(LATERAL_ACCEL / worst) if worst > 1e-4 else float("inf")

    def _stops(self, x, y, heading, v, path, s):
        """Gaps (metres from the AC's centre) to everything it must stop behind."""
        snap = self.world.snapshot
        half = self.world.vehicle.length / 2
        gaps = []
        # whatever stands on our path blocks us, whoever has priority (a car in the way is
        # in the way); priority only decides whom we yield to before they get there
        others = [j for j, vid in enumerate(snap.vehicle_ids) if vid != self.ac]
        # creeping: squeeze past SUMO's cars (never into them); other ACs keep the full margin
        # (they follow the same rules, so index priority resolves them, not squeezing)
        margins = np.array([self._margin(j, heading) for j in others])
        if others:
            oxy = snap.vehicle_xy[others]
            near = np.hypot(oxy[:, 0] - x, oxy[:, 1] - y) < 50.0
            idx = np.array(others)[near]
            margin = margins[near][:, None]
            if len(idx):
                # a car blocks us when any corner of it is within our half width (+ margin)
                # of our path ahead; corners, not centres, so a car half-way through a turn counts
                corners = np.concatenate([
                    rect_corners(*snap.vehicle_xy[j], snap.vehicle_heading[j],
                                 snap.vehicle_length[j], snap.vehicle_width[j]) for j in idx
                ])
                sc, lat = path.project_many(corners)
                sc, lat = sc.reshape(-1, 4), lat.reshape(-1, 4)
                ahead = (sc > s) & (sc - s < 45.0)
                inside = ahead & (np.abs(lat) < self.world.vehicle.width / 2 + margin)
                # a car across our path (corners on both sides of it) blocks us as well
                across = ahead.all(axis=1) & (lat.min(axis=1) < 0) & (lat.max(axis=1) > 0)
                inside |= across[:, None] & ahead
                blocking = inside.any(axis=1)
                for row in np.flatnonzero(blocking):
                    gaps.append(float(sc[row][inside[row]].min()) - s - half)
                rest = [j for j in idx[~blocking] if self._respects(snap.vehicle_ids[j], j, heading)]
                gaps += self._crossing_gaps(x, y, v, path, s, np.array(rest, dtype=int))
        gaps += self._pedestrian_gaps(x, y, path, s)
        gaps += self._ac_conflict_gaps(s)
        tls = self.world.next_tls(self.ac)
        if tls is not None:
            state, dist = tls
            if state in "rRyYu" and dist < 60.0:
                # yellow: go if it cannot stop comfortably before the line
                if state in "yY" and dist < v * v / (2 * COMFORT_DECEL):
                    pass
                else:
                    gaps.append(dist + STOP_MARGIN - 1.0)
        return gaps

    def _pedestrian_gaps(self, x, y, path, s) -> list[float]:
        """Gaps to people: on or about to cross our path, beside the car, or about to be
        on a junction's crossings we are going to enter."""
        snap = self.world.snapshot
        half = self.world.vehicle.length / 2
        half_w = self.world.vehicle.width / 2
        gaps: list[float] = []
        if not len(snap.person_xy):
            return gaps
        near = np.hypot(snap.person_xy[:, 0] - x, snap.person_xy[:, 1] - y) < 35.0
        if near.any():
            # where they are and where they will be in the next 3 s at walking speed:
            # SUMO pedestrians do not avoid cars, so stop before their path, not in it
            ph, pv = snap.person_heading[near], snap.person_speed[near]
            step = np.stack([np.cos(ph), np.sin(ph)], axis=1) * pv[:, None]
            pts = np.concatenate([snap.person_xy[near] + t * step for t in (0.0, 1.0, 2.0, 3.0)])
            # people standing still (waiting at the kerb for us) block only right in front
            reach = np.tile(np.where(pv > 0.2, 1.8, half_w + 0.3), 4)
            if self._creep > 0 or any(c0 - half <= s <= c1 + half
                                      for c0, c1 in self._crossings):
                # squeezing past, or inside a junction's crossings (where it must not
                # wait, see _off_crossings): only what the body would touch
                reach = np.full(len(pts), half_w + PERSON_RADIUS + CREEP_MARGIN)
            sp, lat = path.project_many(pts)
            # people on the sidewalk beside the road do not stop us, unless our body
            # would brush them (a right turn sweeps over the kerb's corner)
            on_road = self.world.roadmap.drivable.lookup(pts)
            near_body = np.abs(lat) < half_w + PERSON_RADIUS + 0.4
            ahead = (sp > s) & (sp - s < 30.0) & (np.abs(lat) < reach) & (on_road | near_body)
            gaps += list(sp[ahead] - s - half - 1.5)
            # before entering a junction's crossings, the whole span must stay clear of
            # people for the next JUNCTION_LOOKAHEAD s: once inside it does not stop
            # for them there (see _off_crossings), so it must not enter to wait
            for c0, c1 in self._crossings:
                entry = c0 - half - 0.5
                if 0.0 <= entry - s < 15.0:
                    later = np.concatenate([snap.person_xy[near] + t * step
                                            for t in np.arange(0.0, JUNCTION_LOOKAHEAD, 0.5)])
                    ls, ll = path.project_many(later)
                    if np.any((ls > c0 - 1.0) & (ls < c1 + 1.0) & (np.abs(ll) < 1.8)):
                        gaps.append(entry - s + STOP_MARGIN)
            # someone walking right beside the car (they walk into its side): stand still
            now = len(pv)  # the first rows of pts are where they are now
            along = np.abs(sp[:now] - s) <= half + 0.5
            walking = (pv > 0.2) & (np.abs(lat[:now]) < half_w + 0.8)
            # one standing against the car: wait, even when creeping (a car never drives
            # into a person, even one that stepped into its side and waits for it)
            touching = np.abs(lat[:now]) < half_w + PERSON_RADIUS + 0.2
            beside = along & (walking | touching)
            if beside.any():
                gaps.append(0.0)
        return gaps

    def _ac_conflict_gaps(self, s: float) -> list[float]:
        """Give way to lower-index ACs whose routes cross or merge with ours, until they pass."""
        gaps = []
        me = self.world.index[self.ac]
        half = self.world.vehicle.length / 2
        # inside a junction's crossings it is committed, as it is for people (_off_crossings):
        # a stop point already behind it would leave it standing on a crossing, where SUMO's
        # people walk into it and then wait for it to leave (a gridlock with the AC it yields to)
        committed = any(c0 - half <= s <= c1 + half for c0, c1 in self._crossings)
        for other in self.world.active:
            j = self.world.index[other]
            if j >= me:
                continue
            conflict = self._conflict(other)
            if conflict is None:
                continue
            my_s, their_s = conflict
            ox, oy, _, vj = self.world.ac_state(other)
            sj, _ = self.world.route(other).path.project(ox, oy)
            to_go = their_s - sj
            # a waiting AC (red light, queue) far from the conflict does not hold us up
            they_approach = -6.0 < to_go < 35.0 and (vj > 1.0 or to_go < 8.0)
            if they_approach and s < my_s - 1.0 and my_s - s < 40.0:
                if vj < 0.2 and self._waits_for_us(other, sj):
                    continue  # they stand because our nose is in their way: yielding deadlocks
                if committed and my_s - s - 4.0 < 0.0:
                    continue
                gaps.append(my_s - s - 4.0)
        return gaps

    def _waits_for_us(self, other: str, their_s: float) -> bool:
        """Whether a corner of our car is on another AC's path in the 45 m ahead of it (within
        its half width + 0.5 m, as _stops measures), so that it stands waiting for us."""
        x, y, heading, _ = self.world.ac_state(self.ac)
        v = self.world.vehicle
        corners = rect_corners(x, y, heading, v.length, v.width)
        sc, lat = self.world.route(other).path.project_many(corners)
        return bool(np.any((sc > their_s) & (sc - their_s < 45.0) & (np.abs(lat) < v.width / 2 + 0.5)))

    def _conflict(self, other: str):
        """(our arc length, their arc length) where the two routes first come within 3 m
        of each other, ignoring a shared start (same lane, car-following handles that)."""
        if other not in self._conflicts:
            mine = self.world.route(self.ac).path
            theirs = self.world.route(other).path
            pts = np.array([mine.point_at(t) for t in np.arange(0, mine.length, 1.0)])
            st, lat = theirs.project_many(pts)
            close = np.flatnonzero(np.abs(lat) < 3.0)
            result = None
            if len(close) and close[0] > 0:
                result = (float(close[0]), float(st[close[0]]))
            self._conflicts[other] = result
        return self._conflicts[other]

    def _respects(self, vid: str, j: int, heading: float) -> bool:
        """Whether to yield to vehicle j before it reaches our path. Same-direction cars
        always count; among ACs crossing or facing each other the lower index goes first
        (so ACs never gridlock). Anything already on our path blocks us regardless.

        After WAIT_BEFORE_CREEP steps standing (not at a red light) it creeps, a gridlock
        breaker (SUMO's cars and pedestrians also wait for the ACs): for CREEP_STEPS steps,
        at most CREEP_SPEED, it passes anything standing that leaves CREEP_MARGIN of room,
        still yielding to moving crossing traffic."""
        if vid == self.ac:
            return False
        snap = self.world.snapshot
        diff = abs((snap.vehicle_heading[j] - heading + math.pi) % (2 * math.pi) - math.pi)
        if diff < math.pi / 4:
            return True
        if snap.vehicle_is_ac[j]:
            return self.world.index[vid] < self.world.index[self.ac]
        return True

    def _margin(self, j: int, heading: float) -> float:
        """Lateral clearance (metres) it wants from vehicle j before passing it."""
        snap = self.world.snapshot
        if snap.vehicle_is_ac[j]:
            return 0.5
        if self._creep > 0:
            return CREEP_MARGIN
        diff = abs((snap.vehicle_heading[j] - heading + math.pi) % (2 * math.pi) - math.pi)
        # a car standing across or against our direction (a left-turner waiting in the
        # junction for us) is passed at STANDING_MARGIN, as a driver would; a leader never
        return STANDING_MARGIN if diff >= math.pi / 4 and snap.vehicle_speed[j] < 0.5 else 0.5

    def _crossing_gaps(self, x, y, v, path, s, idx) -> list[float]:
        """Yield to cars whose straight-line paths meet ours within the horizon."""
        snap = self.world.snapshot
        if len(idx) == 0:
            return []
        ts = np.arange(0.5, self.horizon + 1e-9, 0.5)
        v_self = max(v, 4.0)
        mine = np.array([path.point_at(s + v_self * t) for t in ts])  # (T, 2)
        gaps = []
        for j in idx:
            hj, vj = snap.vehicle_heading[j], snap.vehicle_speed[j]
            if vj < 0.5:
                continue
            if snap.vehicle_is_ac[j]:
                continue  # ACs are handled by route conflicts (_ac_conflict_gaps)
            theirs = snap.vehicle_xy[j] + np.outer(ts * vj, [math.cos(hj), math.sin(hj)])
            d = np.hypot(*(mine - theirs).T)
            hit = np.flatnonzero(d < 3.5)
            if len(hit):
                conflict_s = s + v_self * ts[hit[0]]
                gaps.append(conflict_s - s - 6.0)
        return gaps


def first_turn_stop(world: World, ac: str) -> float | None:
    """Arc length along the AC's route of the stop line before the first junction at which
    the route turns (``cosim.roadmap.movement`` of that pair of edges is not "straight":
    a left or right turn, a roundabout entry), or None for a route that never turns."""
    route = world.route(ac)
    net = world.roadmap.net
    for prev, nxt in zip(route.edges[:-1], route.edges[1:], strict=True):
        if movement(net, [prev, nxt]) == "straight":
            continue
        ends = np.array([ln.getShape()[-1][:2] for ln in net.getEdge(prev).getLanes()])
        along, lat = route.path.project_many(ends)
        return float(along[int(np.argmin(np.abs(lat)))])
    return None


class NonTurner(Autopilot):
    """The ``safe-non-turner`` reference: the autopilot that never turns.

    It drives its lane like :class:`Autopilot` (yielding, lights, people) and, on a
    route that turns, holds with its front bumper behind the stop line of
    the first junction its route turns at (:func:`first_turn_stop`) for the rest of the
    episode. Routes that only go straight (env_1, the main road of env_5, the straight
    slots of env_2 and env_3) it drives to their goals; a roundabout's entry and env_5's
    ramp (it joins at 62 degrees) are turns.
    It shows whether a learner learned to turn (docs/task.md, "Reference policies")."""

    def __init__(self, world: World, ac: str, target_speed: float | None = None,
                 horizon: float = 3.0):
        super().__init__(world, ac, target_speed, horizon)
        self.hold_s = first_turn_stop(world, ac)
        self._holds: dict[str, float | None] = {}  # other ACs' hold lines (first_turn_stop)

    def _waits_for_us(self, other: str, their_s: float) -> bool:
        """Also true of an AC that stands at its own hold line: every AC of the reference is a
        NonTurner, and one holding before its turn never comes (the ramp's ACs of env_5
        would otherwise hold up the main road's for good)."""
        if other not in self._holds:
            self._holds[other] = first_turn_stop(self.world, other)
        hold = self._holds[other]
        front = their_s + self.world.vehicle.length / 2
        return (hold is not None and front > hold - HOLD_MARGIN - 3.0) or super()._waits_for_us(
            other, their_s)

    def _stops(self, x, y, heading, v, path, s):
        gaps = super()._stops(x, y, heading, v, path, s)
        if self.hold_s is not None:
            # a gap g brings the centre to rest at s + g - STOP_MARGIN (see act)
            rest = self.hold_s - self.world.vehicle.length / 2 - HOLD_MARGIN
            gaps.append(rest - s + STOP_MARGIN)
        return gaps
