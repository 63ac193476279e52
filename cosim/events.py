"""Per-AC, per-step events (SPEC §4) and the reward built from them (SPEC §3).

Collisions are footprint overlaps: oriented rectangles for cars, circles for
pedestrians, convex polygons for static road objects. Off-road means a corner
of the footprint leaves the drivable surface; wrong-lane means the centre leaves
the lanes of the AC's own travel direction (junction areas it crosses count as
its own). Both are rasterised once per scenario (:mod:`cosim.roadmap`).

What the world measures, so that only driving pays (docs/scenarios.md):

- the goal is reached only at the goal: within ``goal_radius`` of the goal point
  and on the road (passing the goal's projection somewhere off the road is not enough);
- progress (``dD``) and the forward-speed term ``F`` are credited only while the car
  is on the road and in the lanes of its route: off them, moving towards the goal
  earns nothing (moving away still costs), and what was skipped is not paid later.
  A shortcut across an island, a verge or the wrong side of a roundabout never pays;
- ``red_light``: the step on which the car crosses the stop line of a signalised
  junction on its route while its signal is red (SUMO's signal state).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np

from cosim.geometry import convex_overlap, rect_circle_overlap, rect_corners, rect_corners_many
from cosim.roadmap import RoadMap, Route
from cosim.scenario import RewardWeights
from cosim.sumo_bridge import PERSON_RADIUS, Snapshot

REWARD_TERMS = ("collision", "efficiency", "lane", "step", "red_light")
EVENT_FLAGS = (
    "collision_vehicle", "collision_pedestrian", "collision_object", "off_road", "wrong_lane",
    "red_light", "goal_reached", "out_of_region", "event_vehicle", "event_pedestrian",
    "event_object",
)
"""The per-step boolean events of one AC, in report order (records, CSV counts, CLI).
``collision_*``: in contact this step (the paper's CV/CO/CP count these steps); ``event_*``:
a new collision event starts this step, whoever caused it (what the driving score's infraction
penalty counts); the collision weight charges the AC's own share of them, ``Events.charged_event``
(docs/task.md, "Collision rule")."""
COLLISION_KINDS = ("vehicle", "pedestrian", "object")
RED = "rR"  # SUMO signal states that forbid entering the junction
# A footprint corner may overhang the drivable surface by this much (metres) before the car
# counts as off-road: the kerb and the raster's 0.25 m cells make a harder test flag clean turns.
OFFROAD_TOLERANCE = 0.25
# m/s: below it a car touching a pedestrian is being walked into (SUMO's pedestrians do not
# avoid cars), which is not counted as the car's pedestrian collision
PEDESTRIAN_MIN_SPEED = 0.5


@dataclass
class Events:
    """What happened to one AC in one step."""

    collision_vehicle: bool = False
    collision_pedestrian: bool = False
    collision_object: bool = False
    off_road: bool = False
    wrong_lane: bool = False
    red_light: bool = False
    """Crossed the stop line of a signalised junction on its route against a red signal."""
    goal_reached: bool = False
    out_of_region: bool = False
    distance_to_goal: float = 0.0
    """Metres left along the route to the goal (D)."""
    progress: float = 0.0
    """D(t-1) - D(t), metres."""
    speed: float = 0.0
    """Forward speed, m/s (along the car's heading; never negative: no reverse)."""
    route_speed: float = 0.0
    """Velocity along the route's direction at the car, m/s (negative when driving against it)."""
    hit: str = ""
    """Id of what it collided with this step (first found), for people reading logs."""
    event_vehicle: bool = False
    """A new collision event with a vehicle starts this step (World's per-actor count)."""
    event_pedestrian: bool = False
    event_object: bool = False
    charged_vehicle: bool = False
    """A vehicle event that the reward charges this AC: with Contact.fault "at_fault" (the
    default since task version 5) only one it drove into; with "both" every event_vehicle."""
    route_completion: float = 0.0
    """The AC-episode's route completion so far, 0..1 (cosim/score.py)."""
    new_ground: bool = True
    """This step left the AC nearer its goal than it had been (World's least distance so far):
    only then does the speed term F pay (since task version 5). Re-driving road already driven,
    the metre a blocked car is put back, earns no F (docs/task.md, "Collision rule")."""
    touching: list = field(default_factory=list)
    """(kind, id) of every actor in contact this step, kind in COLLISION_KINDS (not in infos)."""

    @property
    def collision(self) -> bool:
        return self.collision_vehicle or self.collision_pedestrian or self.collision_object

    @property
    def collision_event(self) -> bool:
        """A new collision event of any kind starts this step."""
        return self.event_vehicle or self.event_pedestrian or self.event_object

    @property
    def charged_event(self) -> bool:
        """A collision event the reward charges starts this step: every pedestrian and object
        event, and the vehicle events of Contact.fault (``charged_vehicle``)."""
        return self.charged_vehicle or self.event_pedestrian or self.event_object

    @property
    def lane_violation(self) -> bool:
        """Off the road or outside its own lanes: the OS metric and the lane term."""
        return self.off_road or self.wrong_lane

    def as_dict(self) -> dict:
        # by hand: dataclasses.asdict deep-copies recursively and showed up in profiles
        d = {f: getattr(self, f) for f in _EVENT_FIELDS}
        d["collision"] = self.collision
        d["lane_violation"] = self.lane_violation
        return d


_EVENT_FIELDS = tuple(f.name for f in fields(Events) if f.name != "touching")


def detect_all(
    ac_ids: list[str],
    state: np.ndarray,
    length: float,
    width: float,
    snapshot: Snapshot,
    roadmap: RoadMap,
    routes: list[Route],
    previous_distance: np.ndarray,
    goal_radius: float,
) -> list[Events]:
    """Events of several ACs at once. `state` rows are (x, y, heading, speed).

    Batched over ACs: one distance matrix per kind of obstacle, exact overlap tests
    only for the few close pairs, one raster lookup for every footprint corner.
    """
    n = len(ac_ids)
    xy, heading, speed = state[:, :2], state[:, 2], state[:, 3]
    events = [Events(speed=float(v)) for v in speed]
    corners = rect_corners_many(xy, heading, length, width)
    reach = 0.5 * float(np.hypot(length, width))

    vxy = snapshot.vehicle_xy
    if len(vxy) > 1:
        other_reach = 0.5 * np.hypot(snapshot.vehicle_length, snapshot.vehicle_width)
        d = np.hypot(xy[:, None, 0] - vxy[None, :, 0], xy[:, None, 1] - vxy[None, :, 1])
        for i, j in zip(*np.nonzero(d <= reach + other_reach[None, :]), strict=True):
            ev = events[i]
            if snapshot.vehicle_ids[j] == ac_ids[i]:
                continue
            other = rect_corners(
                vxy[j, 0], vxy[j, 1], snapshot.vehicle_heading[j],
                snapshot.vehicle_length[j], snapshot.vehicle_width[j],
            )
            if convex_overlap(corners[i], other):
                ev.hit = ev.hit if ev.collision_vehicle else snapshot.vehicle_ids[j]
                ev.collision_vehicle = True
                ev.touching.append(("vehicle", snapshot.vehicle_ids[j]))
    pxy = snapshot.person_xy
    if len(pxy):
        # SUMO's pedestrians do not avoid cars: one that walks into a standing car is not
        # the car's collision (docs/scenarios.md); a moving car that touches one is
        d = np.hypot(xy[:, None, 0] - pxy[None, :, 0], xy[:, None, 1] - pxy[None, :, 1])
        for i, j in zip(*np.nonzero(d <= reach + PERSON_RADIUS), strict=True):
            ev = events[i]
            if speed[i] < PEDESTRIAN_MIN_SPEED:
                continue
            if rect_circle_overlap(corners[i], pxy[j, 0], pxy[j, 1], PERSON_RADIUS):
                ev.collision_pedestrian = True
                ev.hit = ev.hit or snapshot.person_ids[j]
                ev.touching.append(("pedestrian", snapshot.person_ids[j]))
    for i, k in roadmap.objects_near_many(xy, reach):
        ev = events[i]
        obj = roadmap.objects[k]
        if convex_overlap(corners[i], obj.polygon):
            ev.collision_object = True
            ev.hit = ev.hit or obj.id
            ev.touching.append(("object", obj.id))

    inner = rect_corners_many(
        xy, heading, length - 2 * OFFROAD_TOLERANCE, width - 2 * OFFROAD_TOLERANCE
    )
    on_road = roadmap.drivable.lookup(inner.reshape(-1, 2)).reshape(n, 4).all(axis=1)
    xmin, ymin, xmax, ymax = roadmap.bounds
    for i, ev in enumerate(events):
        x, y = float(xy[i, 0]), float(xy[i, 1])
        route = routes[i]
        ev.off_road = not bool(on_road[i])
        ev.wrong_lane = not route.lane_mask.value_at(x, y)
        ev.out_of_region = not (xmin <= x <= xmax and ymin <= y <= ymax)
        s = route.arc_length(x, y)
        previous_s = route.goal_s - float(previous_distance[i])
        on_route = not ev.lane_violation
        ev.route_speed = ev.speed * math.cos(float(heading[i]) - route.path.heading_at(s))
        ev.distance_to_goal = max(route.goal_s - s, 0.0)
        ev.progress = float(previous_distance[i]) - ev.distance_to_goal
        if not on_route:
            # off the road or its route's lanes, approaching the goal earns nothing
            ev.progress = min(ev.progress, 0.0)
            ev.route_speed = min(ev.route_speed, 0.0)
        gx, gy = route.goal_point
        ev.goal_reached = (not ev.off_road) and (gx - x) ** 2 + (gy - y) ** 2 <= goal_radius**2
        ev.red_light = on_route and any(
            previous_s < stop_s <= s and is_red(snapshot.signals, tls, link)
            for stop_s, tls, link in route.signals
        )
    return events


def is_red(signals: dict[str, str], tls: str, link: int) -> bool:
    """Whether link `link` of traffic light `tls` shows red in SUMO's state strings."""
    state = signals.get(tls, "")
    return link < len(state) and state[link] in RED


def reward_terms(ev: Events, weights: RewardWeights, speed_limit: float,
                 per_step: bool = False) -> dict[str, float]:
    """The weighted reward terms (docs/task.md, "Collision rule"); the reward is their sum.

    The collision weight charges each new collision event charged to this car
    (``ev.charged_event``: at fault for vehicles by default, Contact.fault), or, with
    ``per_step`` (``Contact.charge == "step"``, task version 3), every step in contact."""
    # F: speed along the route, not along the car's heading, and negative when driving
    # against it, so that circling at speed averages to nothing (policies exploited both
    # the heading version and a [0, 1] clip; see docs/design.md, "F, the speed term")
    forward = min(max(ev.route_speed / speed_limit, -1.0), 1.0)
    if not ev.new_ground:  # road driven before (a car bouncing off what stopped it): no speed credit
        forward = min(forward, 0.0)
    return {
        "collision": weights.collision * float(ev.collision if per_step else ev.charged_event),
        "efficiency": weights.efficiency * (ev.progress + forward),
        "lane": weights.lane * float(ev.lane_violation),
        "step": weights.step,
        "red_light": weights.red_light * float(ev.red_light),
    }
