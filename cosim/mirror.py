"""The PyBullet mirror: the scenario region as a few coloured meshes, the actors as
pooled boxes, and one front camera per learning car (AC).

SUMO simulates the traffic; the mirror only draws it. One :class:`Mirror` owns one
``pybullet.DIRECT`` client (never the global default client) and builds, once:

- the static world from the :class:`~cosim.roadmap.RoadMap` (its meshes come from
  :mod:`cosim.meshes`: road surface, lane markings, raised sidewalks, zebra
  crossings, road objects as extruded prisms); one visual-only body per material
  (no collision shapes), ~10 bodies and 0.8-1.6k triangles per scenario;
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

With ``routes`` (the ``route`` observation variant) :meth:`Mirror.cameras` draws each AC's own
route ahead into its frame: the pixels whose ground footprint lies within ROUTE_WIDTH / 2 of
the route's centreline (:class:`RouteBand`, the camera's own rays) take ROUTE_COLOR. With
TinyRenderer they are part of the backdrop, so whatever the mirror draws (cars, people,
poles, walls) hides them exactly as it hides the ground; with EGL, whose ground is meshes,
they are painted after the render where the depth buffer says the nearest surface is the
ground (lower than ROUTE_GROUND_TOP), so nearer objects hide them too.

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

import atexit
import hashlib
import logging
import math
import os
import re
import shutil
import stat
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cosim.dynamics import VehicleParams
from cosim.errors import SimulatorUnavailable
from cosim.meshes import Mesh, build_static, obj_text
from cosim.roadmap import RoadMap
from cosim.scenario import MAX_ACS
from cosim.sumo_bridge import Snapshot
from cosim.tempfiles import private_folder

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
    "wall": (0.55, 0.32, 0.26, 1.0),  # brick red, darker than buildings
    "island": (0.25, 0.50, 0.22, 1.0),  # planted roundabout island: green, above the grass
    "sign": (0.55, 0.20, 0.65, 1.0),
    "object": (0.60, 0.60, 0.60, 1.0),  # an unknown kind of road object
    "ac": (0.90, 0.08, 0.08, 1.0),
    "car": (0.10, 0.25, 0.90, 1.0),
    "pedestrian": (1.00, 0.55, 0.00, 1.0),
}
GRASS = (84, 140, 60)  # RGB of the backdrop below the horizon
SKY_HORIZON, SKY_ZENITH = (205, 225, 245), (110, 160, 225)  # RGB of the sky backdrop
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
# The route camera (obs="route"; docs/task.md, "The route variant"): an AC's own route ahead,
# drawn on the ground of its own frame (RouteBand).
ROUTE_AHEAD = 40.0  # metres of route from the AC's projection on it (to the goal at most): ~2.9 s at 13.9 m/s
ROUTE_WIDTH = 0.5  # metres: the band on the ground, centred on the route's centreline (a lane is ~3.2 m)
ROUTE_COLOR = (255, 0, 255)  # RGB, unlit: magenta, which no material, the grass or the sky comes near
ROUTE_SPACING = 0.15  # metres between the centreline samples whose discs make the band (edge ripple 1.2 cm)
ROUTE_GROUND_TOP = 0.2  # EGL: a route pixel whose nearest surface is lower (the ground layers, <= 0.15 m) shows it
# Lighting of TinyRenderer: sun high in the south-west, strong ambient so vertical
# faces (car sides, building walls) stay close to their colour.
LIGHT = dict(lightDirection=(-0.4, -0.3, 1.0), lightAmbientCoeff=0.65,
             lightDiffuseCoeff=0.4, lightSpecularCoeff=0.0)


SOFTWARE_GL = r"llvmpipe|softpipe|swrast|swiftshader"  # GL_RENDERER names of CPU rasterisers


class _CapturedStdout:
    """Redirect the process-level stdout (fd 1, where C code prints; ``fd=2``: stderr) to a
    temporary file."""

    def __init__(self, fd: int = 1):
        self._fd = fd
        self._stream = sys.stdout if fd == 1 else sys.stderr

    def __enter__(self) -> _CapturedStdout:
        self.text = ""
        self._file = tempfile.TemporaryFile(mode="w+b")
        try:
            self._stream.flush()
            self._saved = os.dup(self._fd)
            os.dup2(self._file.fileno(), self._fd)
        except (OSError, ValueError, AttributeError):  # no usable fd (closed, or a daemon): capture nothing
            self._saved = None
        return self

    def __exit__(self, *exc) -> None:
        if self._saved is not None:
            try:
                self._stream.flush()
            except (OSError, ValueError, AttributeError):
                pass
            os.dup2(self._saved, self._fd)
            os.close(self._saved)
        self._file.seek(0)
        self.text = self._file.read().decode(errors="replace")
        self._file.close()


def _pybullet():
    """Import pybullet at use, so a missing install is reported when a Mirror starts.

    pybullet's C module prints "pybullet build time: ..." on stderr when it is imported, in
    every process that renders (each env worker, each Ray trial, the test): the import runs
    with fd 2 captured, so no process prints it (issue 28)."""
    try:
        if "pybullet" in sys.modules:
            import pybullet
        else:
            with _CapturedStdout(fd=2) as banner:
                import pybullet
            log.debug("%s", banner.text.strip())
    except ImportError as exc:
        raise SimulatorUnavailable(
            f"pybullet is not importable ({exc}); install it with `pip install 'pybullet>=3.2.6'`"
        ) from exc
    return pybullet


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

    def __init__(self, meshes: dict[str, Mesh], bounds, layers=GROUND_LAYERS,
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
            offset = 0  # Mesh indices count from the mesh's first vertex
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


class RouteBand:
    """Which pixels of a camera show the ground near a route's centreline: the route camera.

    Over flat ground, with the camera's fixed height and pitch and no roll, image row r meets
    the ground on the line ``ahead = F_r`` of the car's heading frame (metres ahead of the eye)
    and its columns step ``t_r / f`` metres across it (t_r: the row's depth along the view,
    f: the focal length in pixels): the rays of :func:`ground_rays`. A pixel is route when its
    ground footprint (its row's span of ``ahead``, its column's span across) touches the band,
    the union of discs of radius ``width / 2`` around centreline samples (:meth:`pixels`): near
    the car the band is exactly ``width`` wide, far away it stays at least a pixel wide instead
    of falling between rows. Every row and sample of every camera is one array operation.
    """

    def __init__(self, size: int, fov_deg: float, width: float = ROUTE_WIDTH):
        self.size, self.half = int(size), float(width) / 2
        f = (size / 2) / math.tan(math.radians(fov_deg) / 2)
        cp, sp = math.cos(CAMERA_PITCH), math.sin(CAMERA_PITCH)

        def ahead(dv):  # metres ahead of the eye where a ray at image height dv meets the ground
            rise = sp + dv * cp
            with np.errstate(divide="ignore"):
                return np.where(rise < -1e-9, CAMERA_HEIGHT / np.maximum(-rise, 1e-12) * (cp - dv * sp),
                                np.inf)

        rows = np.arange(size)
        rise = sp + (size / 2 - rows - 0.5) / f * cp
        self.rows = np.flatnonzero(rise < -1e-6)  # below the horizon: the rows of ground_rays
        self.depth = np.zeros(size)  # each image row's ground depth along the view axis (0: sky)
        self.depth[self.rows] = CAMERA_HEIGHT / -rise[self.rows]
        self.near = ahead((size / 2 - self.rows - 1) / f)  # the row's ground span: its lower edge
        self.far = ahead((size / 2 - self.rows) / f)  # and its upper one (inf at the horizon)
        self.columns_per_metre = f / self.depth[self.rows]  # across the view, in the row
        self._near_up, self._far_up = self.near[::-1].copy(), self.far[::-1].copy()  # ascending
        self._row_start = self.rows * size  # flat index of each row's first pixel

    def pixels(self, points: list[np.ndarray | None]) -> list[np.ndarray]:
        """Per camera, the flat (row-major) indices of its route pixels, some more than once.
        ``points[i]``: that camera's centreline samples (k, 2) as (metres ahead, metres to the
        left) of its eye, or None (no route: no pixels)."""
        out = [np.empty(0, np.int64)] * len(points)
        given = [i for i, p in enumerate(points) if p is not None and len(p)]
        if not given:
            return out
        fwd, left = (np.concatenate([points[i] for i in given]) if len(given) > 1 else points[given[0]]).T
        # the rows whose span of ground ahead comes within half the width of a sample: near and
        # far fall row by row, so they are one run [first, last) of rows per sample
        n_rows = len(self.rows)
        first = n_rows - np.searchsorted(self._near_up, fwd + self.half)
        runs = np.maximum(n_rows - np.searchsorted(self._far_up, fwd - self.half, side="right") - first, 0)
        ends = np.cumsum(runs)
        if ends[-1] == 0:
            return out
        k = np.repeat(np.arange(len(fwd)), runs)  # one (sample, row) pair each
        r = np.arange(ends[-1]) - np.repeat(ends - runs - first, runs)
        gap = np.maximum(np.maximum(self.near[r] - fwd[k], fwd[k] - self.far[r]), 0.0)
        per_metre = self.columns_per_metre[r]
        # the pixels of row r whose footprint (half a column either side) the sample's disc
        # touches (gap < half: the run's rows are those strictly within reach)
        span = 0.5 + np.sqrt(self.half**2 - gap * gap) * per_metre
        centre = (self.size / 2 - 0.5) - left[k] * per_metre  # the sample's column
        c0 = np.maximum(np.ceil(centre - span), 0).astype(np.int64)
        width = np.maximum(np.minimum(np.floor(centre + span) + 1, self.size).astype(np.int64) - c0, 0)
        done = np.cumsum(width)
        flat = np.arange(done[-1]) - np.repeat(done - width - self._row_start[r] - c0, width)
        if len(given) == 1:
            out[given[0]] = flat
            return out
        # samples come camera by camera, so pairs and pixels do too: cut at the cameras' ends
        cut = np.concatenate([[0], done])[np.concatenate([[0], ends])[np.cumsum([len(points[i]) for i in given])]]
        for i, part in zip(given, np.split(flat, cut[:-1]), strict=True):
            out[i] = part
        return out


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


# -- static meshes as files -----------------------------------------------------------------

_MESH_DIR: tuple[int, Path] | None = None  # (owner pid, this process's mesh folder)
_MESH_USERS = 0  # mirrors of this process that are open: the last one's close removes the folder
_MESH_LOCK = threading.Lock()
STALE_MESH_AGE = 600.0
"""Seconds: a ``cosim_meshes_<pid>`` folder of this user's that old, of a process that has ended
(a worker killed with its owner), is removed when a process makes its own."""


def mesh_folder() -> Path:
    """This process's mesh folder, ``<temp>/cosim_meshes_<pid>``: private to this user
    (``cosim.tempfiles.private_folder``), removed when the process's last mirror closes
    (``Mirror.close``, so ``env.close()``) and made again at the same path by the next mirror, so
    that pybullet's cache of mesh files by path still hits (:func:`mesh_file`)."""
    global _MESH_DIR
    pid = os.getpid()
    if _MESH_DIR is None or _MESH_DIR[0] != pid:  # this process's first (a forked child makes its own)
        _remove_stale_mesh_folders()
        _MESH_DIR = (pid, private_folder(f"cosim_meshes_{pid}"))
        atexit.register(_remove_mesh_folder, pid)  # mesh files made without a mirror (tests)
    elif not _MESH_DIR[1].is_dir():
        _MESH_DIR = (pid, private_folder(f"cosim_meshes_{pid}"))
    return _MESH_DIR[1]


def _use_meshes(add: int) -> None:
    """Count a mirror in (+1) or out (-1); the last one out removes this process's mesh folder."""
    global _MESH_USERS
    with _MESH_LOCK:
        _MESH_USERS = max(0, _MESH_USERS + add)
        if add < 0 and _MESH_USERS == 0:
            _remove_mesh_folder(os.getpid())


def _remove_mesh_folder(pid: int) -> None:
    if _MESH_DIR is not None and _MESH_DIR[0] == pid == os.getpid():
        shutil.rmtree(_MESH_DIR[1], ignore_errors=True)


def _remove_stale_mesh_folders() -> None:
    for folder in Path(tempfile.gettempdir()).glob("cosim_meshes_*"):
        pid = folder.name.removeprefix("cosim_meshes_")
        try:
            info = os.lstat(folder)
            if (not pid.isdigit() or not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid()
                    or time.time() - info.st_mtime < STALE_MESH_AGE):
                continue
            os.kill(int(pid), 0)  # raises for a process that has ended
        except ProcessLookupError:
            shutil.rmtree(folder, ignore_errors=True)
        except OSError:  # gone meanwhile, or a process of another user's: not ours to remove
            continue


def mesh_file(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray) -> Path:
    """The OBJ file of one mesh, named by its content and written once per process.

    Static meshes reach pybullet as files, for two measured reasons (pybullet 3.2.7):
    the EGL plugin only draws meshes read from files ("issue extracting mesh"
    otherwise), and ``createVisualShape(vertices=..., indices=..., normals=...)``
    never releases the Python sequences it is given (two extra references on each
    list and row), so every mirror built that way kept ~0.75 MB after ``close()``
    (issue 10; ``bench/env_memory.py``). pybullet caches each mesh file it loads by
    path for the life of the process, so the name is the content's hash: rebuilding
    the same region hits that cache and adds nothing, and the cache is bounded by
    the distinct meshes of the scenarios used. The folder is :func:`mesh_folder`: one path
    for the life of the process (a forked child makes its own), removed while no mirror is open.
    """
    text = obj_text(vertices, triangles, normals)
    path = mesh_folder() / f"{hashlib.sha1(text.encode()).hexdigest()}.obj"
    if not path.exists():
        tmp = path.with_suffix(f".{os.getpid()}.{id(text)}.tmp")
        tmp.write_text(text)
        os.replace(tmp, path)  # atomic: another thread never reads half a file
    return path


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
        self.vehicle: VehicleParams = roadmap.scenario.vehicle
        self._p = _pybullet()
        self._client: int | None = None
        self._egl_plugin = -1
        self._warned_overflow = False
        cid = self._p.connect(self._p.DIRECT)
        if cid < 0:
            raise SimulatorUnavailable(
                "pybullet could not open a DIRECT client; reinstall it with "
                "`pip install --force-reinstall 'pybullet>=3.2.6'`"
            )
        self._client = cid
        self._uses_meshes = False
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
            _use_meshes(+1)
            self._uses_meshes = True
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
        self._route_band = RouteBand(self.image_size, self.fov_deg)
        self._route_rgba = _rgba32(ROUTE_COLOR)
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

    def cameras(self, poses: list[tuple[float, float, float]], routes=None) -> np.ndarray:
        """Front-camera images, one per (x, y, heading) of an AC's centre: uint8 (n, S, S, 3).

        ``routes`` (the route camera): per pose None or that AC's route ahead, centreline
        points (k, 2) in world metres (``Route.ahead``), drawn on the ground of that camera's
        frame alone in ROUTE_COLOR (:class:`RouteBand`; hidden by nearer objects)."""
        p, cid, size = self._p, self._require_open(), self.image_size
        rgba = np.empty((len(poses), size, size, 4), np.uint8)
        eyes = [camera_eye(float(x), float(y), float(h), self.vehicle.length) for x, y, h in poses]
        bands = self._route_pixels(eyes, poses, routes)
        for i, (_, _, heading) in enumerate(poses):
            eye, forward = eyes[i]
            view = p.computeViewMatrix(eye, eye + forward, (0.0, 0.0, 1.0), physicsClientId=cid)
            backdrop = self._camera_backdrop(eye, float(heading))
            band = bands[i] if bands is not None else None
            if band is not None and self._ground is not None:  # TinyRenderer: this camera's backdrop
                backdrop.reshape(-1)[band] = self._route_rgba
            depth = self._render_into(rgba[i], view, self._projection, backdrop)
            if band is not None and self._ground is None:  # EGL: the ground is meshes
                self._paint_route_on_ground(rgba[i], depth, band)
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
        """Disconnect the pybullet client; safe to call twice. The process's last open mirror
        removes the mesh folder (:func:`mesh_folder`)."""
        if getattr(self, "_uses_meshes", False):
            self._uses_meshes = False
            _use_meshes(-1)
        if self._client is None:
            return
        cid, self._client = self._client, None
        try:
            self._p.disconnect(physicsClientId=cid)
        except self._p.error as exc:  # already gone (e.g. the server died): nothing to free
            log.debug("pybullet client %d was already disconnected: %s", cid, exc)

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

    def _build_static(self, meshes: dict[str, Mesh]) -> int:
        """One visual-only body per material (and per MAX_MESH_VERTICES); returns triangles."""
        p, cid = self._p, self._client
        triangles = 0
        for name, mesh in meshes.items():
            for verts, tris, normals in mesh.chunks():
                path = mesh_file(verts, tris, normals)  # a file, not lists: see mesh_file
                shape = p.createVisualShape(p.GEOM_MESH, fileName=str(path),
                                            rgbaColor=COLORS[name], physicsClientId=cid)
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

    def _route_pixels(self, eyes, poses, routes) -> list[np.ndarray] | None:
        """The route pixels of each camera (RouteBand.pixels), or None when no camera has a route."""
        if routes is None or all(r is None for r in routes):
            return None
        if len(routes) != len(poses):
            raise ValueError(f"routes: one entry (None or (k, 2) points) per pose, got {len(routes)} "
                             f"for {len(poses)} poses")
        local = []
        for (eye, _), (_, _, heading), route in zip(eyes, poses, routes, strict=True):
            if route is None:
                local.append(None)
                continue
            c, s = math.cos(float(heading)), math.sin(float(heading))
            d = np.asarray(route, float).reshape(-1, 2) - eye[:2]
            local.append(np.stack([d[:, 0] * c + d[:, 1] * s, d[:, 1] * c - d[:, 0] * s], axis=1))
        return self._route_band.pixels(local)

    def _paint_route_on_ground(self, out: np.ndarray, depth: np.ndarray, band: np.ndarray) -> None:
        """EGL draws the ground as meshes: paint the route pixels whose nearest surface is the
        ground, i.e. where the view ray, at the depth the buffer holds, is lower than
        ROUTE_GROUND_TOP (a car, person or wall in front of the ground point is higher)."""
        d = depth.reshape(-1)[band].astype(np.float64)
        linear = FAR * NEAR / (FAR - (FAR - NEAR) * d)  # eye-space depth of the nearest surface
        ground = self._route_band.depth[band // self.image_size]  # the ground point's depth
        height = CAMERA_HEIGHT * (1.0 - linear / ground)
        shown = band[(d >= _DEPTH_CLEAR) | (height <= ROUTE_GROUND_TOP)]
        out.view(np.uint32).reshape(-1)[shown] = self._route_rgba

    def _park(self, body: int) -> None:
        """Out of sight, and transparent: TinyRenderer skips alpha-0 shapes entirely."""
        p, cid = self._p, self._client
        p.resetBasePositionAndOrientation(body, PARK, (0, 0, 0, 1), physicsClientId=cid)
        p.changeVisualShape(body, -1, rgbaColor=(*self._colors[body][:3], 0.0),
                            physicsClientId=cid)
        self._parked[body] = True

    def _render_into(self, out: np.ndarray, view, projection, backdrop) -> np.ndarray:
        """Render into `out` (H, W, 4) uint8; pixels where nothing was drawn take `backdrop`,
        RGBA packed as uint32 ((H, W) or one value; see :func:`_rgba32`). Returns the depth
        buffer (H, W) float32."""
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
        depth = np.asarray(img[3], np.float32).reshape(height, width)
        # whole pixels as uint32: one masked copy instead of three strided ones
        np.copyto(out.view(np.uint32).reshape(height, width), backdrop, where=depth >= _DEPTH_CLEAR)
        return depth

    def _require_open(self) -> int:
        if self._client is None:
            raise RuntimeError("this Mirror is closed; create a new one")
        return self._client
