"""The PyBullet mirror: the scenario region as a few coloured meshes, the actors as
pooled boxes, and one front camera per learning car (AC).

SUMO simulates the traffic; the mirror only draws it. One :class:`Mirror` owns one
``pybullet.DIRECT`` client (never the global default client) and builds, once:

- the static world from the :class:`~cosim.roadmap.RoadMap`: road surface (lanes +
  junction polygons), lane markings (white dashes between lanes of one direction,
  a yellow centre line between opposite directions), raised sidewalks, zebra
  crossings and the road objects as extruded prisms; one visual-only body per
  material (no collision shapes), ~10 bodies and 0.8-1.6k triangles per scenario;
- a fixed pool of boxes: red ACs, blue background cars, orange pedestrians. Each
  :meth:`Mirror.sync` re-poses them; unused ones are parked far below the ground
  and made transparent, which TinyRenderer skips at no cost. Bodies are never
  created or destroyed after construction;
- no grass or sky geometry: wherever nothing was drawn (depth buffer at its clear
  value) the image takes a backdrop, grass below the horizon and sky above.

Cameras sit 1.4 m high just ahead of the AC's front bumper (so its own box is
behind the eye), look along its heading, 5 degrees down, with a 90 degree field of
view. With the EGL plugin (GPU) every mesh is drawn. With TinyRenderer (CPU) the
flat layers (road, sidewalks, markings, crossings) are hidden and taken instead
from a :class:`GroundRaster`: the same triangles painted top-down into a 0.15 m
colour raster with mip levels. The ground is flat and the camera's height and
pitch are fixed, so every pixel below the horizon meets the ground at a fixed
offset in the car's heading frame: one rotation and one gather per camera.

Measured facts this design rests on (pybullet 3.2.7 TinyRenderer; docs/mirror.md):

- An 84x84 image costs ~0.18 ms empty, plus ~0.17 us per triangle anywhere in the
  scene, plus ~24 ns for every pixel of each triangle's screen bounding box and
  ~0.1 us per shaded pixel. Long thin triangles (lane markings, sidewalk strips,
  road quads near the eye) have huge bounding boxes: the flat layers as meshes
  cost ~1.6 ms per frame, as a raster ~0.06 ms. Big grass and sky quads would cost
  ~1 ms each, hence the backdrop.
- 100 parked opaque boxes cost 0.28 ms per frame; transparent (alpha 0) ones nothing.
- Bodies are drawn in creation order and the depth test comes before shading, so
  occluders are created first.
- It clips triangles against the near plane: a 400 m road quad passing under the
  camera renders like one cut into 2 m pieces (bullet3 issue 1004 was about older
  builds; guarded by a test). It back-face culls (counter-clockwise faces are
  drawn) and clips at the far plane.
- An orthographic projection renders nothing (TinyRenderer reads near/far from a
  perspective matrix), so the overview is a narrow perspective from high above.
"""

from __future__ import annotations

import logging
import math
import os
import re
import sys
import tempfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim.dynamics import VehicleParams
from cosim.errors import SimulatorUnavailable
from cosim.roadmap import LaneInfo, RoadMap
from cosim.scenario import MAX_ACS
from cosim.sumo_bridge import Snapshot

log = logging.getLogger(__name__)

RENDERERS = ("tiny", "egl", "auto")

# Colours (RGBA). Lit surfaces come out at 0.6-1.0 of these (ambient + diffuse light).
COLORS = {
    "road": (0.27, 0.27, 0.29, 1.0),
    "junction": (0.27, 0.27, 0.29, 1.0),
    "white": (0.95, 0.95, 0.95, 1.0),
    "yellow": (0.95, 0.78, 0.10, 1.0),
    "sidewalk": (0.70, 0.70, 0.66, 1.0),
    "walkingarea": (0.70, 0.70, 0.66, 1.0),
    "pole": (0.40, 0.43, 0.36, 1.0),  # olive grey: never mistaken for asphalt
    "guardrail": (0.80, 0.82, 0.86, 1.0),
    "building": (0.72, 0.52, 0.40, 1.0),
    "sign": (0.55, 0.20, 0.65, 1.0),
    "object": (0.60, 0.60, 0.60, 1.0),  # an unknown kind of road object
    "ac": (0.90, 0.08, 0.08, 1.0),
    "car": (0.10, 0.25, 0.90, 1.0),
    "pedestrian": (1.00, 0.55, 0.00, 1.0),
}
GRASS = (84, 140, 60)  # RGB of the backdrop below the horizon
SKY_HORIZON, SKY_ZENITH = (205, 225, 245), (110, 160, 225)  # RGB of the sky backdrop
# Bodies are drawn in creation order and TinyRenderer depth-tests before shading, so
# occluders go first: pool boxes, objects, raised sidewalks, markings, then the layers
# under them.
STATIC_ORDER = ("building", "pole", "guardrail", "sign", "object", "sidewalk", "white", "yellow",
                "road", "walkingarea", "junction")
OBJECT_HEIGHT = {"pole": 5.0, "guardrail": 0.8, "sign": 2.5, "object": 2.0}
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
# the edge. (As meshes they cost ~0.1 ms per TinyRenderer frame, see the docstring.)
EDGE_LINES = False
EDGE_INSET = 0.15  # metres between an edge line and the edge of the asphalt
ZEBRA = 0.5  # metres of each zebra stripe and of each gap
MAX_SEGMENT = 8.0  # longest road/marking quad along a lane (fastest as meshes: 5-10 m)

CAR_HEIGHT = 1.5
PEDESTRIAN_SIZE = (0.5, 0.5, 1.75)  # x, y, z metres
CAMERA_HEIGHT = 1.4
CAMERA_AHEAD = 0.15  # metres in front of the front bumper, so the AC's own box is behind the eye
CAMERA_PITCH = math.radians(-5.0)  # slightly down: more road, less sky
NEAR, FAR = 0.2, 100.0
# Layers TinyRenderer gets from the GroundRaster instead of meshes (EGL draws the meshes).
GROUND_LAYERS = ("junction", "walkingarea", "road", "sidewalk", "white", "yellow")  # paint order
GROUND_RES = 0.15  # metres per texel of the ground raster
GROUND_MARGIN = 20.0  # metres of ground painted beyond the region (cameras stay inside it)
MIP_LEVELS = 5
PARK = (0.0, 0.0, -1000.0)
_DEPTH_CLEAR = 0.9999999  # depth-buffer value where nothing was drawn (both renderers clear to 1)
BOX_TRIANGLES = 12
# Lighting of TinyRenderer: sun high in the south-west, strong ambient so vertical
# faces (car sides, building walls) stay close to their colour.
LIGHT = dict(lightDirection=(-0.4, -0.3, 1.0), lightAmbientCoeff=0.65,
             lightDiffuseCoeff=0.4, lightSpecularCoeff=0.0)
MAX_MESH_VERTICES = 30000  # per visual shape; pybullet refuses very large meshes


SOFTWARE_GL = r"llvmpipe|softpipe|swrast|swiftshader"  # GL_RENDERER names of CPU rasterisers


class _CapturedStdout:
    """Redirect the process-level stdout (fd 1, where C code prints) to a temporary file."""

    def __enter__(self) -> _CapturedStdout:
        self.text = ""
        self._file = tempfile.TemporaryFile(mode="w+b")
        try:
            sys.stdout.flush()
            self._saved = os.dup(1)
            os.dup2(self._file.fileno(), 1)
        except (OSError, ValueError):  # no usable fd 1 (closed, or a daemon): capture nothing
            self._saved = None
        return self

    def __exit__(self, *exc) -> None:
        if self._saved is not None:
            try:
                sys.stdout.flush()
            except (OSError, ValueError):
                pass
            os.dup2(self._saved, 1)
            os.close(self._saved)
        self._file.seek(0)
        self.text = self._file.read().decode(errors="replace")
        self._file.close()


def write_obj(path: Path, vertices: np.ndarray, triangles: np.ndarray,
              normals: np.ndarray) -> None:
    """A Wavefront OBJ of one mesh (vertex normals, 1-based faces)."""
    lines = [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in vertices]
    lines += [f"vn {x:.4f} {y:.4f} {z:.4f}" for x, y, z in normals]
    lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in np.asarray(triangles) + 1]
    Path(path).write_text("\n".join(lines) + "\n")


def _pybullet():
    """Import pybullet at use, so a missing install is reported when a Mirror starts."""
    try:
        import pybullet
    except ImportError as exc:
        raise SimulatorUnavailable(
            f"pybullet is not importable ({exc}); install it with `pip install 'pybullet>=3.2.6'`"
        ) from exc
    return pybullet


# -- geometry helpers (pure numpy) ------------------------------------------------------------


@dataclass
class _Mesh:
    """Triangles of one material, accumulated before they become pybullet shapes."""

    vertices: list
    normals: list
    indices: list
    count: int = 0

    @classmethod
    def empty(cls) -> _Mesh:
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


def build_static(roadmap: RoadMap) -> dict[str, _Mesh]:
    """The region's static meshes, one per material (see the module docstring)."""
    meshes = {name: _Mesh.empty() for name in STATIC_ORDER}
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
        kind = obj.kind if obj.kind in COLORS else "object"
        if kind == "building":
            height = BUILDING_HEIGHTS[zlib.crc32(obj.id.encode()) % len(BUILDING_HEIGHTS)]
        else:
            height = OBJECT_HEIGHT.get(kind, OBJECT_HEIGHT["object"])
        v, t, n = prism(obj.polygon, height)
        meshes[kind].add(v, t, n)
    return meshes


def _add_markings(meshes: dict[str, _Mesh], lanes: list[LaneInfo]) -> None:
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


# -- the ground as a raster (TinyRenderer path) ----------------------------------------------


def _shade_up() -> float:
    """TinyRenderer's light factor on an upward face: ambient + diffuse * cos(sun angle)."""
    lx, ly, lz = LIGHT["lightDirection"]
    return LIGHT["lightAmbientCoeff"] + LIGHT["lightDiffuseCoeff"] * lz / math.sqrt(
        lx * lx + ly * ly + lz * lz)


def _paint_triangle(tex: np.ndarray, tri: np.ndarray, value) -> None:
    """Set the texels of `tex` (rows = y, cols = x, texel centres at integers) inside a
    triangle given in texel coordinates (3, 2)."""
    lo = np.maximum(np.floor(tri.min(axis=0)).astype(int), 0)
    hi = np.minimum(np.ceil(tri.max(axis=0)).astype(int) + 1, (tex.shape[1], tex.shape[0]))
    if lo[0] >= hi[0] or lo[1] >= hi[1]:
        return
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0]), np.arange(lo[1], hi[1]))
    (x0, y0), (x1, y1), (x2, y2) = tri
    area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
    if abs(area) < 1e-12:
        return
    sign = 1.0 if area > 0 else -1.0
    e0 = ((x1 - x0) * (gy - y0) - (y1 - y0) * (gx - x0)) * sign
    e1 = ((x2 - x1) * (gy - y1) - (y2 - y1) * (gx - x1)) * sign
    e2 = ((x0 - x2) * (gy - y2) - (y0 - y2) * (gx - x2)) * sign
    inside = (e0 >= 0) & (e1 >= 0) & (e2 >= 0)
    tex[lo[1]:hi[1], lo[0]:hi[0]][inside] = value


class GroundRaster:
    """The flat layers (road, sidewalks, markings, crossings) painted top-down into a colour
    raster with mip levels, and a lookup of the ground colour each camera pixel sees.

    TinyRenderer spends most of an 84x84 frame on these layers (long, thin triangles
    whose screen bounding boxes it scans pixel by pixel); seen from a fixed height and
    pitch over flat ground, every pixel below the horizon hits the ground at a fixed
    offset in the car's heading frame, so the ground costs one rotation and one gather
    per camera instead. Colours are lit like TinyRenderer lights an upward face.
    """

    def __init__(self, meshes: dict[str, _Mesh], bounds, layers=GROUND_LAYERS,
                 res: float = GROUND_RES, margin: float = GROUND_MARGIN):
        verts = [v for name in layers for v in meshes[name].vertices]
        lo, hi = np.array(bounds[:2], float) - margin, np.array(bounds[2:], float) + margin
        if verts:  # no wider than the layers themselves
            allv = np.concatenate(verts)[:, :2]
            lo, hi = np.maximum(lo, allv.min(axis=0) - 1.0), np.minimum(hi, allv.max(axis=0) + 1.0)
        hi = np.maximum(hi, lo + res)
        self.origin, self.res = lo, res
        shape = (int(math.ceil((hi[1] - lo[1]) / res)), int(math.ceil((hi[0] - lo[0]) / res)))
        tex = np.empty(shape + (3,), np.uint8)
        tex[:] = GRASS
        shade = _shade_up()
        for name in layers:
            value = np.clip(np.array(COLORS[name][:3]) * 255 * shade, 0, 255).astype(np.uint8)
            offset = 0  # _Mesh indices count from the mesh's first vertex
            for v, t in zip(meshes[name].vertices, meshes[name].indices, strict=True):
                texel = (v[:, :2] - lo) / res - 0.5
                for tri in t - offset:
                    _paint_triangle(tex, texel[tri], value)
                offset += len(v)
        levels = [tex]
        img = tex.astype(np.float32)
        for _ in range(1, MIP_LEVELS):
            h, w = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
            if h < 4 or w < 4:
                break
            img = img[:h, :w].reshape(h // 2, 2, w // 2, 2, 3).mean(axis=(1, 3))
            levels.append(np.round(img).astype(np.uint8))
        for level in levels:  # a grass frame: lookups clamped to the edge land on grass
            level[[0, -1]] = GRASS
            level[:, [0, -1]] = GRASS
        # all levels in one flat array of packed RGBA, so one gather serves every pixel
        self.shapes = [level.shape[:2] for level in levels]
        self.offsets = np.cumsum([0] + [h * w for h, w in self.shapes])[:-1]
        self.flat = np.concatenate([_rgba32(level).ravel() for level in levels])

    @property
    def nbytes(self) -> int:
        return self.flat.nbytes

    def view(self, forward: np.ndarray, left: np.ndarray, level: np.ndarray) -> _GroundView:
        """Precompute, for ground points given in a car's heading frame (metres ahead and
        to the left of the eye) and their mip levels, what a per-camera lookup needs."""
        level = np.minimum(level, len(self.shapes) - 1)
        inv = 1.0 / (self.res * (2.0 ** level))
        h = np.array([s[0] for s in self.shapes])[level]
        w = np.array([s[1] for s in self.shapes])[level]
        return _GroundView(inv, forward * inv, left * inv, (w - 1).astype(float),
                           (h - 1).astype(float), self.offsets[level], w)

    def lookup(self, gv: _GroundView, x: float, y: float, heading: float) -> np.ndarray:
        """Packed RGBA of the ground each point of `gv` hits, seen from (x, y, heading)."""
        c, s = math.cos(heading), math.sin(heading)
        col = (x - self.origin[0]) * gv.inv + gv.forward * c - gv.left * s
        row = (y - self.origin[1]) * gv.inv + gv.forward * s + gv.left * c
        np.clip(col, 0.0, gv.col_max, out=col)
        np.clip(row, 0.0, gv.row_max, out=row)
        index = gv.offset + row.astype(np.int64) * gv.width + col.astype(np.int64)
        return self.flat.take(index)


@dataclass(frozen=True)
class _GroundView:
    """Per-pixel constants of a camera's ground lookup (see GroundRaster.view)."""

    inv: np.ndarray  # texels per metre at the pixel's mip level
    forward: np.ndarray  # texels ahead of the eye
    left: np.ndarray  # texels to the left of the eye
    col_max: np.ndarray
    row_max: np.ndarray
    offset: np.ndarray  # start of the level in GroundRaster.flat
    width: np.ndarray


def ground_rays(size: int, fov_deg: float, res: float):
    """Where each below-horizon pixel of a camera meets the ground, in the car's heading frame.

    Returns (pixels, forward, left, level): flat pixel indices, metres ahead of and to
    the left of the eye, and the mip level whose texel matches the pixel's footprint.
    """
    f = (size / 2) / math.tan(math.radians(fov_deg) / 2)
    v, u = np.mgrid[0:size, 0:size] + 0.5
    du, dv = (u - size / 2) / f, (size / 2 - v) / f  # right, up in the image plane
    cp, sp = math.cos(CAMERA_PITCH), math.sin(CAMERA_PITCH)
    # ray = forward_axis + du * right_axis + dv * up_axis, with the axes pitched by CAMERA_PITCH
    ahead = cp - dv * sp
    left = -du
    rise = sp + dv * cp  # vertical component of the ray
    hits = rise < -1e-6
    t = np.where(hits, CAMERA_HEIGHT / np.where(hits, -rise, 1.0), 0.0)
    forward_m, left_m = (t * ahead)[hits], (t * left)[hits]
    dist = np.sqrt(forward_m**2 + left_m**2 + CAMERA_HEIGHT**2)
    lateral = dist / f  # metres one pixel spans across the view
    footprint = lateral / np.sqrt(CAMERA_HEIGHT / dist)  # geometric mean with the along-view span
    level = np.clip(np.floor(np.log2(np.maximum(footprint / res, 1.0))), 0, MIP_LEVELS - 1)
    return np.flatnonzero(hits), forward_m, left_m, level.astype(int)


# -- camera maths ---------------------------------------------------------------------------


def camera_eye(x: float, y: float, heading: float, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Eye position and unit forward direction of the camera of a car centred at (x, y)."""
    c, s = math.cos(heading), math.sin(heading)
    ahead = length / 2 + CAMERA_AHEAD
    eye = np.array([x + c * ahead, y + s * ahead, CAMERA_HEIGHT])
    cp = math.cos(CAMERA_PITCH)
    forward = np.array([c * cp, s * cp, math.sin(CAMERA_PITCH)])
    return eye, forward


def camera_backdrop(size: int, fov_deg: float) -> np.ndarray:
    """The (S, S, 3) image behind everything: sky above the horizon, grass below.

    Row r looks at elevation CAMERA_PITCH + atan((S/2 - r - 0.5) / f) with f the focal
    length in pixels; the ground is flat, so that sign decides sky or grass.
    """
    f = (size / 2) / math.tan(math.radians(fov_deg) / 2)
    rows = np.arange(size) + 0.5
    elevation = CAMERA_PITCH + np.arctan((size / 2 - rows) / f)
    t = np.clip(elevation / math.radians(fov_deg / 2), 0.0, 1.0)[:, None]
    sky = (1 - t) * np.array(SKY_HORIZON) + t * np.array(SKY_ZENITH)
    column = np.where((elevation > 0)[:, None], sky, np.array(GRASS, float))
    return np.repeat(column[:, None, :], size, axis=1).round().astype(np.uint8)


def _rgba32(rgb) -> np.ndarray:
    """RGB (..., 3) uint8-valued -> opaque RGBA packed in uint32 (...), the layout of a
    contiguous (..., 4) uint8 image viewed as uint32."""
    rgb = np.asarray(rgb, np.uint8)
    rgba = np.concatenate([rgb, np.full(rgb.shape[:-1] + (1,), 255, np.uint8)], axis=-1)
    return np.ascontiguousarray(rgba).view(np.uint32)[..., 0]


def _quat_z(heading: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(heading / 2), math.cos(heading / 2))


# -- the mirror -----------------------------------------------------------------------------


class Mirror:
    """A PyBullet picture of one scenario region, with pooled actors and AC cameras.

    Args:
        roadmap: the scenario's static geometry; only its region is built.
        image_size: side S of the square camera images (pixels).
        renderer: "tiny" (CPU TinyRenderer), "egl" (GPU through the eglRenderer
            plugin; raises SimulatorUnavailable when it cannot load) or "auto"
            (EGL when it works, else TinyRenderer; logs which).
        max_cars: background cars drawn at once; ACs have their own pool of MAX_ACS.
        max_pedestrians: pedestrians drawn at once.
        fov_deg: field of view of the AC cameras (degrees, horizontal = vertical).

    Raises:
        SimulatorUnavailable: pybullet is missing/broken or EGL was asked for and fails.
        ValueError: a bad argument, named with the accepted values.
    """

    def __init__(self, roadmap: RoadMap, *, image_size: int = 84, renderer: str = "tiny",
                 max_cars: int = 40, max_pedestrians: int = 40, fov_deg: float = 90.0):
        if renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {renderer!r}")
        if not 8 <= int(image_size) <= 1024:
            raise ValueError(f"image_size must be 8..1024 pixels, got {image_size}")
        if max_cars < 0 or max_pedestrians < 0:
            raise ValueError("max_cars and max_pedestrians must be >= 0")
        if not 10.0 <= fov_deg <= 170.0:
            raise ValueError(f"fov_deg must be 10..170 degrees, got {fov_deg}")
        self.roadmap = roadmap
        self.image_size = int(image_size)
        self.fov_deg = float(fov_deg)
        self.vehicle = VehicleParams()
        self._p = _pybullet()
        self._client: int | None = None
        self._tmpdir: tempfile.TemporaryDirectory | None = None
        self._egl_plugin = -1
        self._warned_overflow = False
        cid = self._p.connect(self._p.DIRECT)
        if cid < 0:
            raise SimulatorUnavailable(
                "pybullet could not open a DIRECT client; reinstall it with "
                "`pip install --force-reinstall 'pybullet>=3.2.6'`"
            )
        self._client = cid
        try:
            self.renderer = self._select_renderer(renderer)
            size = (self.vehicle.length / 2, self.vehicle.width / 2, CAR_HEIGHT / 2)
            self._ac_pool = self._build_pool(MAX_ACS, size, COLORS["ac"])
            self._car_pool = self._build_pool(max_cars, size, COLORS["car"])
            ped = tuple(v / 2 for v in PEDESTRIAN_SIZE)
            self._ped_pool = self._build_pool(max_pedestrians, ped, COLORS["pedestrian"])
            self._ground_bodies: dict[int, tuple] = {}
            self._ground_triangles = 0
            meshes = build_static(roadmap)
            self._static_triangles = self._build_static(meshes)
            self._ground = None
            if self.renderer == "tiny":
                # TinyRenderer takes the flat layers from a raster (see GroundRaster)
                self._show_ground_meshes(False)
                self._ground = GroundRaster(meshes, roadmap.bounds)
                pix, fwd, left, level = ground_rays(self.image_size, self.fov_deg, GROUND_RES)
                self._ground_pixels = pix
                self._ground_view = self._ground.view(fwd, left, level)
        except BaseException:
            self.close()
            raise
        self._parked = {b: True for b in self._ac_pool + self._car_pool + self._ped_pool}
        self._colors = {}
        for pool, kind in ((self._ac_pool, "ac"), (self._car_pool, "car"),
                           (self._ped_pool, "pedestrian")):
            self._colors.update({b: COLORS[kind] for b in pool})
        self._projection = self._p.computeProjectionMatrixFOV(
            self.fov_deg, 1.0, NEAR, FAR, physicsClientId=cid
        )
        self._backdrop = _rgba32(camera_backdrop(self.image_size, self.fov_deg))
        log.info("mirror of %s: %d triangles, renderer %s", roadmap.scenario.name,
                 self.triangle_count, self.renderer)

    # -- public API ---------------------------------------------------------------------------
    @property
    def client(self) -> int | None:
        """The pybullet client id; None once closed."""
        return self._client

    @property
    def triangle_count(self) -> int:
        """Triangles in the scene: static meshes and every pool body, parked or not."""
        pool = len(self._ac_pool) + len(self._car_pool) + len(self._ped_pool)
        return self._static_triangles + BOX_TRIANGLES * pool

    def sync(self, snapshot: Snapshot) -> None:
        """Re-pose the pool to a snapshot; more actors than a pool holds: the nearest to the
        region centre are drawn (logged once)."""
        is_ac = np.asarray(snapshot.vehicle_is_ac, bool)
        xy = np.asarray(snapshot.vehicle_xy, float).reshape(-1, 2)
        heading = np.asarray(snapshot.vehicle_heading, float)
        self._pose(self._ac_pool, xy[is_ac], heading[is_ac], CAR_HEIGHT / 2, "ACs")
        self._pose(self._car_pool, xy[~is_ac], heading[~is_ac], CAR_HEIGHT / 2, "cars")
        pxy = np.asarray(snapshot.person_xy, float).reshape(-1, 2)
        self._pose(self._ped_pool, pxy, np.asarray(snapshot.person_heading, float),
                   PEDESTRIAN_SIZE[2] / 2, "pedestrians")

    def cameras(self, poses: list[tuple[float, float, float]]) -> np.ndarray:
        """Front-camera images, one per (x, y, heading) of an AC's centre: uint8 (n, S, S, 3)."""
        p, cid, size = self._p, self._require_open(), self.image_size
        rgba = np.empty((len(poses), size, size, 4), np.uint8)
        for i, (x, y, heading) in enumerate(poses):
            heading = float(heading)
            eye, forward = camera_eye(float(x), float(y), heading, self.vehicle.length)
            view = p.computeViewMatrix(eye, eye + forward, (0.0, 0.0, 1.0), physicsClientId=cid)
            self._render_into(rgba[i], view, self._projection, self._camera_backdrop(eye, heading))
        return rgba[..., :3].copy()

    def overview(self, size: tuple[int, int] = (320, 320), center=None, extent=None) -> np.ndarray:
        """Top-down RGB picture (north up), uint8 (H, W, 3) for size = (W, H).

        Args:
            size: (width, height) in pixels.
            center: (x, y) the picture is centred on; default the region centre.
            extent: metres the picture spans across its width; default fits the region.
        """
        p, cid = self._p, self._require_open()
        w, h = int(size[0]), int(size[1])
        xmin, ymin, xmax, ymax = self.roadmap.bounds
        cx, cy = center if center is not None else ((xmin + xmax) / 2, (ymin + ymax) / 2)
        if extent is None:
            extent = 1.04 * max(xmax - xmin, (ymax - ymin) * w / h)
        half_w, half_h = extent / 2, extent / 2 * h / w
        # TinyRenderer needs a perspective matrix: a narrow one from far above is nearly
        # orthographic (the region edge is seen 1.4 degrees off vertical).
        height = 40.0 * max(half_w, half_h)
        near = height - 60.0
        k = near / height
        proj = p.computeProjectionMatrix(-half_w * k, half_w * k, -half_h * k, half_h * k,
                                         near, height + 10.0, physicsClientId=cid)
        view = p.computeViewMatrix((cx, cy, height), (cx, cy, 0.0), (0.0, 1.0, 0.0),
                                   physicsClientId=cid)
        rgba = np.empty((h, w, 4), np.uint8)
        if self._ground is not None:  # the overview is rare: draw the flat layers as meshes
            self._show_ground_meshes(True)
        try:
            self._render_into(rgba, view, proj, _rgba32(GRASS))
        finally:
            if self._ground is not None:
                self._show_ground_meshes(False)
        return rgba[..., :3].copy()

    def close(self) -> None:
        """Disconnect the pybullet client; safe to call twice."""
        if self._client is None:
            return
        cid, self._client = self._client, None
        try:
            self._p.disconnect(physicsClientId=cid)
        except self._p.error as exc:  # already gone (e.g. the server died): nothing to free
            log.debug("pybullet client %d was already disconnected: %s", cid, exc)
        if self._tmpdir is not None:
            self._tmpdir.cleanup()
            self._tmpdir = None

    def __enter__(self) -> Mirror:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- construction -------------------------------------------------------------------------
    def _select_renderer(self, renderer: str) -> str:
        if renderer == "tiny":
            return "tiny"
        ok, why, gl = self._load_egl()
        software = bool(re.search(SOFTWARE_GL, gl, re.IGNORECASE))
        if ok and software and renderer == "auto":
            # Mesa's CPU rasteriser behind EGL is far slower than TinyRenderer
            self._p.unloadPlugin(self._egl_plugin, physicsClientId=self._client)
            log.info("mirror renders with TinyRenderer (CPU): EGL is software (%s)", gl)
            return "tiny"
        if ok:
            if software:
                log.warning("EGL renders in software (%s): slower than renderer='tiny'", gl)
            else:
                log.info("mirror renders with EGL (%s)", gl or "GPU")
            return "egl"
        if renderer == "egl":
            raise SimulatorUnavailable(
                f"the pybullet eglRenderer plugin cannot be used ({why}); it needs a GPU with "
                "EGL drivers (NVIDIA: libnvidia-egl; `pip install pybullet` ships the plugin). "
                "Use renderer='tiny' (CPU) or 'auto'."
            )
        log.info("mirror renders with TinyRenderer (CPU): EGL unavailable (%s)", why)
        return "tiny"

    def _load_egl(self) -> tuple[bool, str, str]:
        """Load the EGL plugin before any visual shape exists (shapes made earlier are not
        uploaded to it). Returns (ok, why not, GL_RENDERER as the plugin printed it)."""
        import importlib.util

        spec = importlib.util.find_spec("eglRenderer")
        if spec is None or not spec.origin:
            return False, "module eglRenderer not found", ""
        # the plugin prints its GL vendor/renderer on the C stdout: read it, and keep it
        # out of the user's console
        with _CapturedStdout() as out:
            plugin = self._p.loadPlugin(spec.origin, "_eglRendererPlugin",
                                        physicsClientId=self._client)
            ok, why = plugin >= 0, "" if plugin >= 0 else "loadPlugin failed"
            if ok:
                try:  # a plugin that loads without a usable EGL device fails to render
                    img = self._p.getCameraImage(8, 8, renderer=self._p.ER_BULLET_HARDWARE_OPENGL,
                                                 physicsClientId=self._client)
                    ok = img is not None and len(img) >= 3
                    why = "" if ok else "test render returned nothing"
                except self._p.error as exc:
                    ok, why = False, f"test render failed: {exc}"
                if not ok:
                    self._p.unloadPlugin(plugin, physicsClientId=self._client)
        self._egl_plugin = plugin
        match = re.search(r"GL_RENDERER=(.*)", out.text)
        return ok, why, match.group(1).strip() if match else ""

    def _build_static(self, meshes: dict[str, _Mesh]) -> int:
        """One visual-only body per material (and per MAX_MESH_VERTICES); returns triangles."""
        p, cid = self._p, self._client
        triangles = 0
        for name, mesh in meshes.items():
            for k, (verts, tris, normals) in enumerate(mesh.chunks()):
                if self.renderer == "egl":
                    # the EGL plugin only draws meshes read from files (in-memory vertices
                    # give "issue extracting mesh" and nothing on screen)
                    if self._tmpdir is None:
                        self._tmpdir = tempfile.TemporaryDirectory(prefix="cosim_mirror_")
                    path = Path(self._tmpdir.name) / f"{name}_{k}.obj"
                    write_obj(path, verts, tris, normals)
                    shape = p.createVisualShape(p.GEOM_MESH, fileName=str(path),
                                                rgbaColor=COLORS[name], physicsClientId=cid)
                else:
                    shape = p.createVisualShape(
                        p.GEOM_MESH, vertices=verts.tolist(), indices=tris.ravel().tolist(),
                        normals=normals.tolist(), rgbaColor=COLORS[name], physicsClientId=cid,
                    )
                body = p.createMultiBody(0, baseCollisionShapeIndex=-1,
                                         baseVisualShapeIndex=shape, physicsClientId=cid)
                if name in GROUND_LAYERS:
                    self._ground_bodies[body] = COLORS[name]
                    self._ground_triangles += len(tris)
                triangles += len(tris)
        return triangles

    def _show_ground_meshes(self, show: bool) -> None:
        for body, rgba in self._ground_bodies.items():
            self._p.changeVisualShape(body, -1, rgbaColor=rgba if show else (*rgba[:3], 0.0),
                                      physicsClientId=self._client)

    def _build_pool(self, n: int, half_extents, rgba) -> list[int]:
        if n == 0:
            return []
        p, cid = self._p, self._client
        # born parked: transparent until a sync shows it
        shape = p.createVisualShape(p.GEOM_BOX, halfExtents=half_extents,
                                    rgbaColor=(*rgba[:3], 0.0), physicsClientId=cid)
        return [p.createMultiBody(0, -1, shape, basePosition=PARK, physicsClientId=cid)
                for _ in range(n)]

    # -- per step -----------------------------------------------------------------------------
    def _pose(self, pool: list[int], xy: np.ndarray, heading: np.ndarray, z: float,
              what: str) -> None:
        p, cid = self._p, self._require_open()
        if len(xy) > len(pool):
            if not self._warned_overflow:
                log.warning("%d %s but a pool of %d: drawing the nearest to the region centre "
                            "(raise max_cars / max_pedestrians to draw all)", len(xy), what,
                            len(pool))
                self._warned_overflow = True
            xmin, ymin, xmax, ymax = self.roadmap.bounds
            d = np.hypot(xy[:, 0] - (xmin + xmax) / 2, xy[:, 1] - (ymin + ymax) / 2)
            keep = np.argsort(d, kind="stable")[: len(pool)]
            xy, heading = xy[keep], heading[keep]
        for body, (x, y), h in zip(pool, xy, heading, strict=False):
            p.resetBasePositionAndOrientation(body, (float(x), float(y), z), _quat_z(float(h)),
                                              physicsClientId=cid)
            if self._parked[body]:
                p.changeVisualShape(body, -1, rgbaColor=self._colors[body], physicsClientId=cid)
                self._parked[body] = False
        for body in pool[len(xy):]:
            if not self._parked[body]:
                self._park(body)

    def _camera_backdrop(self, eye: np.ndarray, heading: float) -> np.ndarray:
        """Sky, and below the horizon the ground raster as this camera sees it (packed RGBA)."""
        if self._ground is None:
            return self._backdrop
        backdrop = self._backdrop.copy()
        backdrop.reshape(-1)[self._ground_pixels] = self._ground.lookup(
            self._ground_view, eye[0], eye[1], heading)
        return backdrop

    def _park(self, body: int) -> None:
        """Out of sight, and transparent: TinyRenderer skips alpha-0 shapes entirely."""
        p, cid = self._p, self._client
        p.resetBasePositionAndOrientation(body, PARK, (0, 0, 0, 1), physicsClientId=cid)
        p.changeVisualShape(body, -1, rgbaColor=(*self._colors[body][:3], 0.0),
                            physicsClientId=cid)
        self._parked[body] = True

    def _render_into(self, out: np.ndarray, view, projection, backdrop) -> None:
        """Render into `out` (H, W, 4) uint8; pixels where nothing was drawn take `backdrop`,
        RGBA packed as uint32 ((H, W) or one value; see :func:`_rgba32`)."""
        p = self._p
        height, width = out.shape[:2]
        if self.renderer == "egl":
            img = p.getCameraImage(width, height, view, projection,
                                   renderer=p.ER_BULLET_HARDWARE_OPENGL,
                                   flags=p.ER_NO_SEGMENTATION_MASK, physicsClientId=self._client)
        else:
            img = p.getCameraImage(width, height, view, projection, renderer=p.ER_TINY_RENDERER,
                                   shadow=0, flags=p.ER_NO_SEGMENTATION_MASK,
                                   physicsClientId=self._client, **LIGHT)
        out[...] = np.asarray(img[2], np.uint8).reshape(height, width, 4)
        empty = np.asarray(img[3], np.float32).reshape(height, width) >= _DEPTH_CLEAR
        # whole pixels as uint32: one masked copy instead of three strided ones
        np.copyto(out.view(np.uint32).reshape(height, width), backdrop, where=empty)

    def _require_open(self) -> int:
        if self._client is None:
            raise RuntimeError("this Mirror is closed; create a new one")
        return self._client
