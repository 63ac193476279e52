"""The static world as triangle meshes, one per material (pure numpy).

From a :class:`~cosim.roadmap.RoadMap`: the road surface (lanes and junction
polygons), lane markings (white dashes between lanes of one direction, a yellow
centre line between opposite directions), raised sidewalks and walking areas,
zebra crossings, and the road objects as extruded prisms. :func:`build_static`
returns them as :class:`Mesh` accumulators; :mod:`cosim.mirror` turns them into
pybullet visual shapes (EGL path) and paints the flat ones into its ground raster
(TinyRenderer path). Nothing here imports pybullet.
"""

from __future__ import annotations

import logging
import math
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim.roadmap import LaneInfo, RoadMap

log = logging.getLogger(__name__)

MAX_MESH_VERTICES = 30000  # per visual shape; pybullet refuses very large meshes

# Bodies are drawn in creation order and TinyRenderer depth-tests before shading, so
# occluders go first: pool boxes, objects, raised sidewalks, markings, then the layers
# under them.
STATIC_ORDER = ("building", "wall", "island", "pole", "guardrail", "sign", "object", "sidewalk",
                "white", "yellow",
                "road", "walkingarea", "junction")
OBJECT_HEIGHT = {"pole": 5.0, "guardrail": 0.8, "sign": 2.5, "object": 2.0,
                 "wall": 1.5, "island": 0.8}  # wall: the building line; island: kerb + planting
OBJECT_KINDS = ("building", *OBJECT_HEIGHT)  # others are drawn as a generic "object"
BUILDING_HEIGHTS = (8.0, 11.0, 14.0, 17.0, 20.0)  # picked per building by a hash of its id

# Heights above the ground (z = 0): far enough apart that TinyRenderer's depth test
# never confuses them at 100 m, low enough to look flat from 1.4 m.
# Junction polygons, then walking areas, then lanes: SUMO's walking areas cover a
# junction's corners but can also span the carriageway where a sidewalk meets a
# junction without a crossing (env_4's roundabout entries); the lanes win there.
Z_JUNCTION, Z_WALKINGAREA, Z_ROAD, Z_MARK, Z_SIDEWALK = 0.01, 0.02, 0.03, 0.06, 0.15
MARK_WIDTH = 0.2  # metres; wider than real (0.12-0.15) so a line 10 m ahead still hits a pixel at 84x84
CENTRE_WIDTH = 0.3  # metres of the yellow centre line (one line, read as a double one at 84 px)
DASH, GAP = 3.0, 6.0  # metres of a dashed lane line
# Edge lines add two long strips per edge; the asphalt/sidewalk contrast already marks
# the edge. (As meshes they cost ~0.1 ms per TinyRenderer frame; cosim/mirror.py.)
EDGE_LINES = False
EDGE_INSET = 0.15  # metres between an edge line and the edge of the asphalt
ZEBRA = 0.5  # metres of each zebra stripe and of each gap
MAX_SEGMENT = 8.0  # longest road/marking quad along a lane (fastest as meshes: 5-10 m)


def obj_text(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray) -> str:
    """A Wavefront OBJ of one mesh (vertex normals, 1-based faces), as text."""
    lines = [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in vertices]
    lines += [f"vn {x:.4f} {y:.4f} {z:.4f}" for x, y, z in normals]
    lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in np.asarray(triangles) + 1]
    return "\n".join(lines) + "\n"


def write_obj(path: Path, vertices: np.ndarray, triangles: np.ndarray,
              normals: np.ndarray) -> None:
    """Write :func:`obj_text` of one mesh to ``path``."""
    Path(path).write_text(obj_text(vertices, triangles, normals))




@dataclass
class Mesh:
    """Triangles of one material, accumulated before they become pybullet shapes."""

    vertices: list
    normals: list
    indices: list
    count: int = 0

    @classmethod
    def empty(cls) -> Mesh:
        return cls([], [], [])

    def add(self, vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray) -> None:
        """Append vertices (k, 3), triangles (m, 3) indexing them, normals (k, 3)."""
        if len(triangles) == 0:
            return
        self.vertices.append(np.asarray(vertices, float))
        self.normals.append(np.asarray(normals, float))
        self.indices.append(np.asarray(triangles, int) + self.count)
        self.count += len(vertices)

    @property
    def triangles(self) -> int:
        return sum(len(t) for t in self.indices)

    def chunks(self):
        """(vertices, indices, normals) arrays of at most MAX_MESH_VERTICES vertices each."""
        start = 0
        verts, norms, tris = [], [], []
        for v, n, t in zip(self.vertices, self.normals, self.indices, strict=True):
            if verts and sum(len(a) for a in verts) + len(v) > MAX_MESH_VERTICES:
                yield np.concatenate(verts), np.concatenate(tris) - start, np.concatenate(norms)
                start += sum(len(a) for a in verts)
                verts, norms, tris = [], [], []
            verts.append(v)
            norms.append(n)
            tris.append(t)
        if verts:
            yield np.concatenate(verts), np.concatenate(tris) - start, np.concatenate(norms)


def _clean(points: np.ndarray, closed: bool = False) -> np.ndarray:
    """Drop repeated points (and the closing point of a ring)."""
    pts = np.asarray(points, float)[:, :2]
    keep = np.ones(len(pts), bool)
    keep[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6
    pts = pts[keep]
    if closed and len(pts) > 1 and np.linalg.norm(pts[0] - pts[-1]) < 1e-6:
        pts = pts[:-1]
    return pts


def _cut(shape: np.ndarray, s0: float, s1: float, max_len: float | None = None) -> np.ndarray:
    """Points of a polyline between arc lengths s0 < s1, keeping its vertices, no piece longer
    than max_len (default MAX_SEGMENT)."""
    max_len = MAX_SEGMENT if max_len is None else max_len
    seg = np.linalg.norm(np.diff(shape, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    inner = cum[(cum > s0) & (cum < s1)]
    s = np.concatenate([[s0], inner, [s1]])
    pieces = [s[:1]]
    for a, b in zip(s[:-1], s[1:], strict=True):
        n = max(1, math.ceil((b - a) / max_len - 1e-9))
        pieces.append(np.linspace(a, b, n + 1)[1:])
    s = np.concatenate(pieces)
    return np.column_stack([np.interp(s, cum, shape[:, 0]), np.interp(s, cum, shape[:, 1])])


def _left_normals(points: np.ndarray) -> np.ndarray:
    """Left normals at each point of a polyline, mitred at the joints (longer than 1 in a
    bend, so a ribbon keeps its width)."""
    d = np.diff(points, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    seg_n = np.column_stack([-d[:, 1], d[:, 0]])
    n = np.empty_like(points)
    n[0], n[-1] = seg_n[0], seg_n[-1]
    mid = seg_n[:-1] + seg_n[1:]
    # mitre: scale so the ribbon keeps its width through a bend (capped for hairpins)
    cos_half = np.clip(np.linalg.norm(mid, axis=1) / 2, 0.5, 1.0)
    mid /= np.linalg.norm(mid, axis=1, keepdims=True) + 1e-12
    n[1:-1] = mid / cos_half[:, None]
    return n


def ribbon(shape: np.ndarray, left: float, right: float, z: float, s0: float = 0.0,
           s1: float | None = None):
    """A flat strip along a polyline between lateral offsets `right` < `left` (metres, + = left).

    Returns (vertices (k, 3), triangles (m, 3)), counter-clockwise seen from above.
    """
    shape = _clean(shape)
    if len(shape) < 2:
        return np.zeros((0, 3)), np.zeros((0, 3), int)
    length = float(np.linalg.norm(np.diff(shape, axis=0), axis=1).sum())
    s1 = length if s1 is None else min(s1, length)
    if s1 - s0 < 1e-3:
        return np.zeros((0, 3)), np.zeros((0, 3), int)
    pts = _cut(shape, s0, s1)
    n = _left_normals(pts)
    k = len(pts)
    xy = np.concatenate([pts + n * right, pts + n * left])  # right side 0..k-1, left side k..2k-1
    verts = np.column_stack([xy, np.full(2 * k, z)])
    i = np.arange(k - 1)
    tris = np.concatenate([
        np.column_stack([i, i + 1, k + i + 1]),
        np.column_stack([i, k + i + 1, k + i]),
    ])
    return verts, tris


def dashes(shape: np.ndarray, left: float, right: float, z: float, dash: float, gap: float):
    """Ribbon pieces of length `dash` every `dash + gap` metres along a polyline."""
    shape = _clean(shape)
    if len(shape) < 2:
        return np.zeros((0, 3)), np.zeros((0, 3), int)
    length = float(np.linalg.norm(np.diff(shape, axis=0), axis=1).sum())
    verts, tris, count = [], [], 0
    # centre the pattern so both ends of a lane look alike
    period = dash + gap
    n = max(1, int((length + gap) // period))
    start = (length - (n * period - gap)) / 2
    for j in range(n):
        a = start + j * period
        v, t = ribbon(shape, left, right, z, max(a, 0.0), a + dash)
        verts.append(v)
        tris.append(t + count)
        count += len(v)
    return np.concatenate(verts), np.concatenate(tris)


def _signed_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def triangulate(polygon: np.ndarray) -> np.ndarray:
    """Ear-clipping triangulation of a simple polygon; triangles (m, 3) counter-clockwise.

    Indices refer to the polygon as given (minus repeated points, see :func:`_clean`);
    call on ``_clean(polygon, closed=True)``.
    """
    poly = np.asarray(polygon, float)
    n = len(poly)
    if n < 3:
        return np.zeros((0, 3), int)
    order = list(range(n)) if _signed_area(poly) > 0 else list(range(n - 1, -1, -1))
    tris = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(order) > 3 and guard < 4 * n * n:
        guard += 1
        m = len(order)
        for k in range(m):
            i0, i1, i2 = order[k - 1], order[k], order[(k + 1) % m]
            a, b, c = poly[i0], poly[i1], poly[i2]
            if cross(a, b, c) <= 1e-12:
                continue  # reflex or collinear corner: not an ear
            inside = False
            for j in order:
                if j in (i0, i1, i2):
                    continue
                p = poly[j]
                if cross(a, b, p) >= 0 and cross(b, c, p) >= 0 and cross(c, a, p) >= 0:
                    inside = True
                    break
            if not inside:
                tris.append((i0, i1, i2))
                order.pop(k)
                break
        else:
            break  # no ear left: not a simple polygon
    if len(order) > 3:
        log.debug("polygon of %d points is not simple; fan-filling the rest", n)
        tris += [(order[0], order[j], order[j + 1]) for j in range(1, len(order) - 1)]
    elif len(order) == 3:
        tris.append(tuple(order))
    return np.array(tris, int).reshape(-1, 3)


def flat_polygon(polygon: np.ndarray, z: float):
    """A horizontal polygon at height z: (vertices (k, 3), triangles (m, 3))."""
    poly = _clean(polygon, closed=True)
    tris = triangulate(poly)
    return np.column_stack([poly, np.full(len(poly), z)]), tris


def prism(polygon: np.ndarray, height: float):
    """A convex polygon extruded from z=0 to `height`: (vertices, triangles, normals).

    The top shares no vertices with the sides so each face is lit by its own normal.
    """
    poly = _clean(polygon, closed=True)
    if _signed_area(poly) < 0:
        poly = poly[::-1]
    k = len(poly)
    top = np.column_stack([poly, np.full(k, height)])
    verts = [top]
    normals = [np.tile([0.0, 0.0, 1.0], (k, 1))]
    tris = [np.column_stack([np.zeros(k - 2, int), np.arange(1, k - 1), np.arange(2, k)])]
    base = k
    for j in range(k):
        a, b = poly[j], poly[(j + 1) % k]
        d = b - a
        out = np.array([d[1], -d[0], 0.0]) / (np.hypot(*d) + 1e-12)
        verts.append(np.array([[*a, 0.0], [*b, 0.0], [*b, height], [*a, height]]))
        normals.append(np.tile(out, (4, 1)))
        tris.append(np.array([[base, base + 1, base + 2], [base, base + 2, base + 3]]))
        base += 4
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(normals)


def _up(verts: np.ndarray) -> np.ndarray:
    return np.tile([0.0, 0.0, 1.0], (len(verts), 1))


def _opposite(edge: str) -> str | None:
    """SUMO edges are named <road>_<dir>; the opposite direction of x_e is x_w, of x_n is x_s."""
    road, _, d = edge.rpartition("_")
    flip = {"e": "w", "w": "e", "n": "s", "s": "n"}.get(d)
    return f"{road}_{flip}" if road and flip else None


def build_static(roadmap: RoadMap) -> dict[str, Mesh]:
    """The region's static meshes, one per material (see the module docstring)."""
    meshes = {name: Mesh.empty() for name in STATIC_ORDER}
    for lane in roadmap.lanes:
        v, t = ribbon(lane.shape, lane.width / 2, -lane.width / 2, Z_ROAD)
        meshes["road"].add(v, t, _up(v))
    for poly in roadmap.junctions.values():
        v, t = flat_polygon(poly, Z_JUNCTION)
        meshes["junction"].add(v, t, _up(v))
    _add_markings(meshes, roadmap.lanes)
    for walk in roadmap.sidewalks:
        if walk.is_internal:  # a walking area: its shape is the outline
            v, t = flat_polygon(walk.shape, Z_WALKINGAREA)
            meshes["walkingarea"].add(v, t, _up(v))
        else:
            v, t = ribbon(walk.shape, walk.width / 2, -walk.width / 2, Z_SIDEWALK)
            meshes["sidewalk"].add(v, t, _up(v))
    for crossing in roadmap.crossings:
        half = crossing.width / 2 - 0.2
        v, t = dashes(crossing.shape, half, -half, Z_MARK, ZEBRA, ZEBRA)
        meshes["white"].add(v, t, _up(v))
    for obj in roadmap.objects:
        kind = obj.kind if obj.kind in OBJECT_KINDS else "object"
        if kind == "building":
            height = BUILDING_HEIGHTS[zlib.crc32(obj.id.encode()) % len(BUILDING_HEIGHTS)]
        else:
            height = OBJECT_HEIGHT.get(kind, OBJECT_HEIGHT["object"])
        v, t, n = prism(obj.polygon, height)
        meshes[kind].add(v, t, n)
    return meshes


def _add_markings(meshes: dict[str, Mesh], lanes: list[LaneInfo]) -> None:
    """White dashes between lanes of one direction; one yellow centre line per two-way road;
    white edge lines only if EDGE_LINES (the asphalt/sidewalk contrast marks the edge)."""
    by_edge: dict[str, list[LaneInfo]] = {}
    for lane in lanes:
        if not lane.is_internal:  # junction interiors carry no markings
            by_edge.setdefault(lane.edge, []).append(lane)
    hw = MARK_WIDTH / 2
    for edge, group in by_edge.items():
        group.sort(key=lambda ln: ln.index)  # SUMO: index 0 = rightmost
        right, left = group[0], group[-1]
        for lane in group[1:]:
            # the boundary between a lane and the one to its right, as seen from the left lane
            off = -lane.width / 2
            v, t = dashes(lane.shape, off + hw, off - hw, Z_MARK, DASH, GAP)
            meshes["white"].add(v, t, _up(v))
        opposite = _opposite(edge)
        if opposite in by_edge:
            if edge < opposite:  # draw the shared centre line once, from one side
                off = left.width / 2
                half = CENTRE_WIDTH / 2
                v, t = ribbon(left.shape, off + half, off - half, Z_MARK)
                meshes["yellow"].add(v, t, _up(v))
        elif EDGE_LINES:
            off = left.width / 2 - EDGE_INSET - hw
            v, t = ribbon(left.shape, off + hw, off - hw, Z_MARK)
            meshes["white"].add(v, t, _up(v))
        if EDGE_LINES:
            off = -right.width / 2 + EDGE_INSET + hw
            v, t = ribbon(right.shape, off + hw, off - hw, Z_MARK)
            meshes["white"].add(v, t, _up(v))
