"""The static world of one scenario, precomputed once: lanes, routes, road objects.

Built from the SUMO network with sumolib and cached per process. It answers the
per-step geometric questions cheaply: is a point on the drivable surface, is it in
the lanes of this AC's travel direction, how far along its route is an AC, which
static objects are near.
"""

from __future__ import annotations

import functools
import logging
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim.errors import NetError, ScenarioError
from cosim.geometry import Polyline, Raster, SegmentField
from cosim.scenario import ACSpec, Scenario

log = logging.getLogger(__name__)

SPAWN_GAP = 1.0  # metres kept free between two ACs' spawn footprints
RASTER_RESOLUTION = 0.25  # metres per cell: a fraction of the 0.6-0.7 m lane margin
VEHICLE_CLASS = "passenger"


@dataclass(frozen=True)
class RoadObject:
    """A static object a car can hit: pole, guardrail, building, sign."""

    id: str
    kind: str
    polygon: np.ndarray  # (k, 2), convex
    centre: np.ndarray  # (2,)
    radius: float  # bounding circle


@dataclass(frozen=True)
class Route:
    """One AC's path: SUMO edges, centreline, spawn pose and goal."""

    edges: tuple[str, ...]
    sumo_lane: int  # SUMO lane index on the first edge (sidewalks count in SUMO's numbering)
    path: Polyline
    spawn_s: float
    goal_s: float
    lane_mask: Raster  # lanes of its own travel direction (+ junctions it crosses)

    field: SegmentField | None = None
    signals: tuple[tuple[float, str, int], ...] = ()
    """(arc length of the stop line, traffic light id, link index) per signalised junction."""

    def arc_length(self, x: float, y: float) -> float:
        """Arc length along the route of the point nearest to (x, y)."""
        if self.field is None:
            return self.path.project(x, y)[0]
        return self.field.project(x, y)

    def ahead(self, x: float, y: float, length: float, spacing: float) -> np.ndarray:
        """The centreline from the route's point nearest to (x, y) on for ``length`` metres, up
        to the goal: its points (k, 2) at the multiples of ``spacing`` metres of arc length in
        that stretch, none past the goal (what the route camera draws, cosim.mirror.RouteBand;
        docs/task.md, "The route variant"). The route is sampled once per spacing."""
        s = self.arc_length(x, y)
        table = self._samples.get(spacing)
        if table is None:
            table = self._samples[spacing] = self.path.at(np.arange(math.floor(self.goal_s / spacing) + 1) * spacing)
        return table[math.ceil(s / spacing):math.floor(min(s + length, self.goal_s) / spacing) + 1]

    @functools.cached_property
    def _samples(self) -> dict[float, np.ndarray]:
        """spacing -> the route's points at every multiple of it up to the goal (:meth:`ahead`)."""
        return {}

    @functools.cached_property
    def goal_point(self) -> tuple[float, float]:
        gx, gy = self.path.point_at(self.goal_s)
        return float(gx), float(gy)

    @functools.cached_property
    def spawn_xy(self) -> np.ndarray:
        return self.path.point_at(self.spawn_s)

    @property
    def spawn_heading(self) -> float:
        return self.path.heading_at(self.spawn_s)

    @property
    def goal_xy(self) -> np.ndarray:
        return self.path.point_at(self.goal_s)


@dataclass(frozen=True)
class LaneInfo:
    """A drivable lane of the region, for the mirror to draw."""

    id: str
    shape: np.ndarray
    width: float
    edge: str
    index: int  # SUMO lane index
    is_internal: bool


class RoadMap:
    """Static geometry of a scenario's region (see module docstring)."""

    def __init__(self, scenario: Scenario):
        self.scenario = scenario
        self.net = read_net(scenario.net)
        xmin, ymin, xmax, ymax = scenario.region.bounds
        self.bounds = (xmin, ymin, xmax, ymax)
        self.lanes = [ln for ln in _region_lanes(self.net, self.bounds)]
        self.sidewalks = _region_sidewalks(self.net, self.bounds)
        self.crossings = _region_crossings(self.net, self.bounds)
        self.junctions = _region_junction_shapes(self.net, self.bounds)
        self.drivable = Raster(self.bounds, RASTER_RESOLUTION)
        for lane in self.lanes:
            self.drivable.paint_polyline(lane.shape, lane.width / 2)
        for shape in self.junctions.values():
            self.drivable.paint_polygon(shape)
        self.objects = tuple(
            o for path in scenario.additional for o in read_objects(path) if _near(o, self.bounds)
        )
        self._object_centres = (
            np.array([o.centre for o in self.objects]) if self.objects else np.zeros((0, 2))
        )
        self._object_radii = np.array([o.radius for o in self.objects])
        self.routes = tuple(self._build_route(i, ac) for i, ac in enumerate(scenario.acs))
        self._check_spawns_and_goals()

    # -- queries ---------------------------------------------------------------
    def objects_near_many(self, xy: np.ndarray, reach: float) -> list[tuple[int, int]]:
        """(row of xy, object index) pairs whose bounding circles come within `reach`."""
        if not self.objects:
            return []
        c = self._object_centres
        d = np.hypot(xy[:, None, 0] - c[None, :, 0], xy[:, None, 1] - c[None, :, 1])
        return list(zip(*np.nonzero(d <= self._object_radii[None, :] + reach), strict=True))

    # -- construction ----------------------------------------------------------
    def _check_spawns_and_goals(self) -> None:
        """Refuse spawns or goals outside the region and spawn poses that overlap.

        Two ACs overlap when, in the first one's frame, they are closer than a car
        length + SPAWN_GAP along it and a car width + SPAWN_GAP / 2 across it (cars
        side by side in adjacent lanes are fine); they would collide at step 1.
        """
        where = self.scenario.source or self.scenario.name
        region = self.scenario.region
        for i, route in enumerate(self.routes):
            for what, key, (x, y) in (("spawn", "depart_pos", route.spawn_xy),
                                      ("goal", "arrival_pos", route.goal_xy)):
                if not region.contains(x, y):
                    raise ScenarioError(
                        f"{where}: acs[{i}].{key}: the {what} point ({x:.1f}, {y:.1f}) is outside the "
                        f"region (center {list(region.center)}, size {list(region.size)}); move "
                        f"{key} or enlarge region.size"
                    )
        car = self.scenario.vehicle
        for i, a in enumerate(self.routes):
            h = a.spawn_heading
            for j in range(i + 1, len(self.routes)):
                dx, dy = self.routes[j].spawn_xy - a.spawn_xy
                along = abs(dx * math.cos(h) + dy * math.sin(h))
                across = abs(-dx * math.sin(h) + dy * math.cos(h))
                if along < car.length + SPAWN_GAP and across < car.width + SPAWN_GAP / 2:
                    raise ScenarioError(
                        f"{where}: acs[{i}] and acs[{j}] spawn {math.hypot(dx, dy):.1f} m apart, closer "
                        f"than a car ({car.length} m + {SPAWN_GAP} m gap): they would collide at "
                        f"the first step; change acs[{j}].depart_pos or lane"
                    )

    def _build_route(self, index: int, ac: ACSpec) -> Route:
        where = f"{self.scenario.source or self.scenario.name}: acs[{index}]"
        edges = []
        for eid in ac.route:
            if not self.net.hasEdge(eid):
                raise ScenarioError(f"{where}: route edge {eid!r} is not in {self.scenario.net.name}")
            edges.append(self.net.getEdge(eid))
        drivable = [ln for ln in edges[0].getLanes() if ln.allows(VEHICLE_CLASS)]
        if ac.lane >= len(drivable):
            raise ScenarioError(
                f"{where}: lane {ac.lane} does not exist on edge {edges[0].getID()!r}, "
                f"which has {len(drivable)} car lane(s) (0 = rightmost)"
            )
        lane = drivable[ac.lane]
        points = [np.asarray(lane.getShape(), dtype=float)]
        mask = Raster(self.bounds, RASTER_RESOLUTION)
        for e in edges:
            for ln in e.getLanes():
                if ln.allows(VEHICLE_CLASS):
                    mask.paint_polyline(np.asarray(ln.getShape()), ln.getWidth() / 2)
        start_len = lane.getLength()
        stop_lines = []  # (stop-line point, tls id, link index)
        for prev, nxt in zip(edges[:-1], edges[1:], strict=True):
            conns = [c for c in prev.getOutgoing().get(nxt, [])]
            if not conns:
                raise ScenarioError(
                    f"{where}: route edges {prev.getID()!r} -> {nxt.getID()!r} are not connected "
                    f"in {self.scenario.net.name}; list consecutive, connected edges"
                )
            conn = next((c for c in conns if c.getFromLane() == lane), conns[0])
            if conn.getTLSID():
                stop_lines.append((np.asarray(conn.getFromLane().getShape()[-1][:2], dtype=float),
                                   conn.getTLSID(), conn.getTLLinkIndex()))
            via = conn.getViaLaneID()
            if via:
                via_lane = self.net.getLane(via)
                points.append(np.asarray(via_lane.getShape(), dtype=float))
                mask.paint_polyline(np.asarray(via_lane.getShape()), via_lane.getWidth() / 2)
            junction = prev.getToNode().getID()
            if junction in self.junctions:
                mask.paint_polygon(self.junctions[junction])
            lane = conn.getToLane()
            points.append(np.asarray(lane.getShape(), dtype=float))
        path = Polyline.from_points(np.concatenate(points))
        first_len = start_len
        depart = ac.depart_pos if ac.depart_pos >= 0 else first_len + ac.depart_pos
        last_len = lane.getLength()
        arrival = ac.arrival_pos if ac.arrival_pos >= 0 else last_len + ac.arrival_pos
        if not 0 <= depart <= first_len:
            raise ScenarioError(
                f"{where}: depart_pos {ac.depart_pos} is outside edge {edges[0].getID()!r} "
                f"(length {first_len:.1f} m)"
            )
        if not 0 <= arrival <= last_len:
            raise ScenarioError(
                f"{where}: arrival_pos {ac.arrival_pos} is outside edge {edges[-1].getID()!r} "
                f"(length {last_len:.1f} m)"
            )
        goal_s = path.length - (last_len - arrival)
        if goal_s <= depart:
            raise ScenarioError(f"{where}: the goal lies behind the spawn point on the route")
        signals = tuple((float(path.project(*p)[0]), tls, int(link)) for p, tls, link in stop_lines)
        return Route(
            edges=tuple(ac.route),
            sumo_lane=drivable[ac.lane].getIndex(),
            path=path,
            spawn_s=float(depart),
            goal_s=float(goal_s),
            lane_mask=mask,
            field=SegmentField(path, self.bounds),
            signals=signals,
        )


def movement(net, edges) -> str:
    """What a route does at its junction(s): "straight", "left", "right" or "u-turn".

    Read from the SUMO network's geometry: the heading change between the end of the
    first edge and the start of the last one (so a roundabout's first / second / third
    exit reads right / straight / left, whatever SUMO calls each connection).
    """
    def heading(shape, at_end: bool) -> float:
        (x0, y0), (x1, y1) = (shape[-2][:2], shape[-1][:2]) if at_end else (shape[0][:2], shape[1][:2])
        return math.atan2(y1 - y0, x1 - x0)

    first, last = net.getEdge(edges[0]), net.getEdge(edges[-1])
    if len(edges) == 1:
        return "straight"
    turn = heading(last.getShape(), False) - heading(first.getShape(), True)
    turn = math.degrees((turn + math.pi) % (2 * math.pi) - math.pi)
    if abs(turn) < 30:
        return "straight"
    if abs(turn) > 150:
        return "u-turn"
    return "left" if turn > 0 else "right"


@functools.lru_cache(maxsize=8)
def _read_net_cached(path: str, mtime: float):
    import sumolib  # deferred: a broken SUMO install is reported when the simulation starts

    try:
        return sumolib.net.readNet(path, withInternal=True, withPedestrianConnections=True)
    except Exception as exc:  # sumolib raises xml.sax and plain exceptions alike
        raise NetError(
            f"{path}: cannot read the SUMO network ({exc}); rebuild it with `cosim nets build` "
            "or fix the XML"
        ) from exc


def read_net(path: Path):
    """Read (and cache) a SUMO network with its internal junction lanes."""
    path = Path(path)
    if not path.exists():
        raise NetError(f"network file {path} does not exist; run `cosim nets build`")
    net = _read_net_cached(str(path), path.stat().st_mtime)
    if not net.getEdges():
        raise NetError(f"{path}: the network has no edges; is it a SUMO .net.xml file?")
    return net


@functools.lru_cache(maxsize=8)
def _road_map_cached(scenario: Scenario) -> RoadMap:
    return RoadMap(scenario)


def road_map(scenario: Scenario) -> RoadMap:
    """The (cached) RoadMap of a scenario."""
    return _road_map_cached(scenario)


def read_objects(path: Path) -> list[RoadObject]:
    """Static road objects: the closed polygons of a SUMO additional file."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise NetError(f"{path}: malformed additional file: {exc}") from exc
    objects = []
    for poly in root.iter("poly"):
        pid = poly.get("id", "?")
        try:
            pts = np.array(
                [[float(v) for v in p.split(",")[:2]] for p in poly.get("shape", "").split()]
            )
        except ValueError as exc:
            raise NetError(f"{path}: poly {pid!r} has a malformed shape: {exc}") from exc
        if pts.ndim != 2 or len(pts) < 3:
            raise NetError(f"{path}: poly {pid!r} needs a shape of at least 3 points")
        if np.allclose(pts[0], pts[-1]):
            pts = pts[:-1]
        centre = pts.mean(axis=0)
        radius = float(np.max(np.linalg.norm(pts - centre, axis=1)))
        objects.append(RoadObject(pid, poly.get("type", "object"), pts, centre, radius))
    return objects


def _near(obj: RoadObject, bounds, margin: float = 5.0) -> bool:
    xmin, ymin, xmax, ymax = bounds
    x, y = obj.centre
    r = obj.radius + margin
    return xmin - r <= x <= xmax + r and ymin - r <= y <= ymax + r


def _in_bounds(shape, bounds, margin: float = 10.0) -> bool:
    xmin, ymin, xmax, ymax = bounds
    pts = np.asarray(shape)
    return bool(
        np.any(
            (pts[:, 0] >= xmin - margin)
            & (pts[:, 0] <= xmax + margin)
            & (pts[:, 1] >= ymin - margin)
            & (pts[:, 1] <= ymax + margin)
        )
    )


def _region_lanes(net, bounds) -> list[LaneInfo]:
    out = []
    for edge in net.getEdges(withInternal=True):
        if edge.getFunction() in ("walkingarea", "crossing"):
            continue
        for ln in edge.getLanes():
            if ln.allows(VEHICLE_CLASS) and _in_bounds(ln.getShape(), bounds):
                out.append(
                    LaneInfo(
                        ln.getID(),
                        np.asarray(ln.getShape(), dtype=float),
                        ln.getWidth(),
                        edge.getID(),
                        ln.getIndex(),
                        edge.getFunction() == "internal",
                    )
                )
    return out


def _region_sidewalks(net, bounds) -> list[LaneInfo]:
    out = []
    for edge in net.getEdges(withInternal=True):
        if edge.getFunction() == "crossing":
            continue
        for ln in edge.getLanes():
            if (
                ln.allows("pedestrian")
                and not ln.allows(VEHICLE_CLASS)
                and _in_bounds(ln.getShape(), bounds)
            ):
                out.append(
                    LaneInfo(ln.getID(), np.asarray(ln.getShape(), dtype=float), ln.getWidth(),
                             edge.getID(), ln.getIndex(), edge.getFunction() != "")
                )
    return out


def _region_crossings(net, bounds) -> list[LaneInfo]:
    out = []
    for edge in net.getEdges(withInternal=True):
        if edge.getFunction() != "crossing":
            continue
        for ln in edge.getLanes():
            if _in_bounds(ln.getShape(), bounds):
                out.append(
                    LaneInfo(ln.getID(), np.asarray(ln.getShape(), dtype=float), ln.getWidth(),
                             edge.getID(), ln.getIndex(), True)
                )
    return out


def _region_junction_shapes(net, bounds) -> dict[str, np.ndarray]:
    out = {}
    for node in net.getNodes():
        shape = node.getShape()
        if node.getType() == "dead_end" or len(shape) < 3 or not _in_bounds(shape, bounds):
            continue
        out[node.getID()] = np.asarray(shape, dtype=float)[:, :2]
    return out
