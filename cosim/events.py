"""Per-AC, per-step events (SPEC §4) and the reward built from them (SPEC §3).

Collisions are footprint overlaps: oriented rectangles for cars, circles for
pedestrians, convex polygons for static road objects. Off-road means a corner
of the footprint leaves the drivable surface; wrong-lane means the centre leaves
the lanes of the AC's own travel direction (junction areas it crosses count as
its own). Both are rasterised once per scenario (:mod:`cosim.roadmap`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from cosim.geometry import convex_overlap, rect_circle_overlap, rect_corners
from cosim.roadmap import RoadMap, Route
from cosim.scenario import RewardWeights
from cosim.sumo_bridge import PERSON_RADIUS, Snapshot

REWARD_TERMS = ("collision", "efficiency", "lane", "step")
# A footprint corner may overhang the drivable surface by this much (metres) before the car
# counts as off-road: the kerb and the raster's 0.25 m cells make a harder test flag clean turns.
OFFROAD_TOLERANCE = 0.25


@dataclass
class Events:
    """What happened to one AC in one step."""

    collision_vehicle: bool = False
    collision_pedestrian: bool = False
    collision_object: bool = False
    off_road: bool = False
    wrong_lane: bool = False
    goal_reached: bool = False
    out_of_region: bool = False
    distance_to_goal: float = 0.0
    """Metres left along the route to the goal (D)."""
    progress: float = 0.0
    """D(t-1) - D(t), metres."""
    speed: float = 0.0
    """Forward speed, m/s."""
    hit: str = ""
    """Id of what it collided with this step (first found), for people reading logs."""

    @property
    def collision(self) -> bool:
        return self.collision_vehicle or self.collision_pedestrian or self.collision_object

    @property
    def lane_violation(self) -> bool:
        """Off the road or outside its own lanes: the OS metric and the lane term."""
        return self.off_road or self.wrong_lane

    def as_dict(self) -> dict:
        d = asdict(self)
        d["collision"] = self.collision
        d["lane_violation"] = self.lane_violation
        return d


def detect(
    ac_id: str,
    x: float,
    y: float,
    heading: float,
    speed: float,
    length: float,
    width: float,
    snapshot: Snapshot,
    roadmap: RoadMap,
    route: Route,
    previous_distance: float,
    goal_radius: float,
) -> Events:
    """Events of one AC (its own row in the snapshot is skipped for vehicle collisions)."""
    ev = Events(speed=speed)
    corners = rect_corners(x, y, heading, length, width)
    reach = 0.5 * float(np.hypot(length, width))

    # vehicles: cheap circle test first, exact oriented-rectangle test on the few left
    vxy = snapshot.vehicle_xy
    if len(vxy):
        other_reach = 0.5 * np.hypot(snapshot.vehicle_length, snapshot.vehicle_width)
        d = np.hypot(vxy[:, 0] - x, vxy[:, 1] - y)
        for j in np.flatnonzero(d <= reach + other_reach):
            if snapshot.vehicle_ids[j] == ac_id:
                continue
            other = rect_corners(
                vxy[j, 0], vxy[j, 1], snapshot.vehicle_heading[j],
                snapshot.vehicle_length[j], snapshot.vehicle_width[j],
            )
            if convex_overlap(corners, other):
                ev.collision_vehicle = True
                ev.hit = snapshot.vehicle_ids[j]
                break
    pxy = snapshot.person_xy
    if len(pxy):
        d = np.hypot(pxy[:, 0] - x, pxy[:, 1] - y)
        for j in np.flatnonzero(d <= reach + PERSON_RADIUS):
            if rect_circle_overlap(corners, pxy[j, 0], pxy[j, 1], PERSON_RADIUS):
                ev.collision_pedestrian = True
                ev.hit = ev.hit or snapshot.person_ids[j]
                break
    for obj in roadmap.objects_near(x, y, reach):
        if convex_overlap(corners, obj.polygon):
            ev.collision_object = True
            ev.hit = ev.hit or obj.id
            break

    inner = rect_corners(
        x, y, heading, length - 2 * OFFROAD_TOLERANCE, width - 2 * OFFROAD_TOLERANCE
    )
    ev.off_road = not bool(roadmap.drivable.lookup(inner).all())
    ev.wrong_lane = not bool(route.lane_mask.lookup(np.array([[x, y]]))[0])
    ev.out_of_region = not roadmap.scenario.region.contains(x, y)

    s, _lateral = route.path.project(x, y)
    ev.distance_to_goal = max(route.goal_s - s, 0.0)
    ev.progress = previous_distance - ev.distance_to_goal
    goal = route.goal_xy
    ev.goal_reached = bool(
        np.hypot(goal[0] - x, goal[1] - y) <= goal_radius or ev.distance_to_goal <= 0.0
    )
    return ev


def reward_terms(ev: Events, weights: RewardWeights, speed_limit: float) -> dict[str, float]:
    """The weighted reward terms of SPEC §3; the reward is their sum."""
    forward = min(max(ev.speed / speed_limit, 0.0), 1.0)
    return {
        "collision": weights.collision * float(ev.collision),
        "efficiency": weights.efficiency * (ev.progress + forward),
        "lane": weights.lane * float(ev.lane_violation),
        "step": weights.step,
    }
