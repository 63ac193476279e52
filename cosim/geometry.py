"""Plane geometry for events: oriented footprints, overlap tests, polylines, rasters.

Pure numpy functions, tested on hand-made shapes. Angles are radians,
counter-clockwise from the x axis (east); SUMO's compass angles are converted
at the bridge.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np


@functools.lru_cache(maxsize=16)
def _local_corners(length: float, width: float) -> tuple[np.ndarray, np.ndarray]:
    hl, hw = length / 2, width / 2
    return np.array([hl, hl, -hl, -hl]), np.array([-hw, hw, hw, -hw])


def rect_corners_many(xy: np.ndarray, heading: np.ndarray, length: float, width: float) -> np.ndarray:
    """Corners (n, 4, 2) of n equal oriented rectangles centred at xy (n, 2), counter-clockwise."""
    lx, ly = _local_corners(float(length), float(width))
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    out = np.empty((len(xy), 4, 2))
    out[:, :, 0] = xy[:, 0:1] + c * lx - s * ly
    out[:, :, 1] = xy[:, 1:2] + s * lx + c * ly
    return out


def rect_corners(x: float, y: float, heading: float, length: float, width: float) -> np.ndarray:
    """Corners (4, 2) of an oriented rectangle centred at (x, y), counter-clockwise."""
    return rect_corners_many(np.array([[x, y]], dtype=float), np.array([heading], dtype=float),
                             length, width)[0]


def convex_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test: do two convex polygons (k, 2) overlap (touching counts)?

    Plain Python over the few vertices: for 4-8 points numpy's per-call overhead
    costs more than the arithmetic (this runs for every close pair every step).
    """
    pa = [(float(x), float(y)) for x, y in a]
    pb = [(float(x), float(y)) for x, y in b]
    for poly in (pa, pb):
        n = len(poly)
        for k in range(n):
            x0, y0 = poly[k]
            x1, y1 = poly[(k + 1) % n]
            nx, ny = y0 - y1, x1 - x0  # edge normal (length does not matter)
            amin = amax = pa[0][0] * nx + pa[0][1] * ny
            for x, y in pa[1:]:
                v = x * nx + y * ny
                amin, amax = min(amin, v), max(amax, v)
            bmin = bmax = pb[0][0] * nx + pb[0][1] * ny
            for x, y in pb[1:]:
                v = x * nx + y * ny
                bmin, bmax = min(bmin, v), max(bmax, v)
            if amax < bmin or bmax < amin:
                return False
    return True


def rect_circle_overlap(corners: np.ndarray, cx: float, cy: float, radius: float) -> bool:
    """Does an oriented rectangle (its 4 corners, in order) overlap a circle?"""
    origin = corners[0]
    u = corners[1] - origin
    v = corners[3] - origin
    p = np.array([cx, cy]) - origin
    lu, lv = float(u @ u), float(v @ v)
    tu = min(max(float(p @ u) / lu, 0.0), 1.0)
    tv = min(max(float(p @ v) / lv, 0.0), 1.0)
    nearest = origin + tu * u + tv * v
    return float(np.hypot(*(nearest - (cx, cy)))) <= radius


@dataclass(frozen=True)
class Polyline:
    """A path with cumulative arc length, for progress along a route."""

    points: np.ndarray  # (n, 2)
    cumlen: np.ndarray  # (n,)

    @classmethod
    def from_points(cls, points: np.ndarray) -> Polyline:
        pts = np.asarray(points, dtype=float)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6])
        pts = pts[keep]
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        return cls(pts, np.concatenate([[0.0], np.cumsum(seg)]))

    @property
    def length(self) -> float:
        return float(self.cumlen[-1])

    def project(self, x: float, y: float) -> tuple[float, float]:
        """(arc length of the nearest point, signed lateral offset, + = left of travel)."""
        a, b = self.points[:-1], self.points[1:]
        d = b - a
        seglen2 = np.einsum("ij,ij->i", d, d)
        p = np.array([x, y])
        t = np.clip(np.einsum("ij,ij->i", p - a, d) / seglen2, 0.0, 1.0)
        nearest = a + t[:, None] * d
        dist2 = np.einsum("ij,ij->i", p - nearest, p - nearest)
        i = int(np.argmin(dist2))
        cross = d[i, 0] * (y - a[i, 1]) - d[i, 1] * (x - a[i, 0])
        lateral = float(np.sqrt(dist2[i])) * (1.0 if cross >= 0 else -1.0)
        return float(self.cumlen[i] + t[i] * np.sqrt(seglen2[i])), lateral

    def project_many(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised :meth:`project` for points (k, 2): (arc lengths, signed lateral offsets)."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        a, d = self.points[:-1], np.diff(self.points, axis=0)
        seglen2 = np.einsum("ij,ij->i", d, d)
        rel = pts[:, None, :] - a[None, :, :]  # (k, m, 2)
        t = np.clip(np.einsum("kmj,mj->km", rel, d) / seglen2, 0.0, 1.0)
        off = rel - t[..., None] * d[None]
        dist2 = np.einsum("kmj,kmj->km", off, off)
        i = np.argmin(dist2, axis=1)
        k = np.arange(len(pts))
        cross = d[i, 0] * rel[k, i, 1] - d[i, 1] * rel[k, i, 0]
        lateral = np.sqrt(dist2[k, i]) * np.where(cross >= 0, 1.0, -1.0)
        return self.cumlen[i] + t[k, i] * np.sqrt(seglen2[i]), lateral

    def point_at(self, s: float) -> np.ndarray:
        """The point at arc length s (clamped to the ends)."""
        s = min(max(s, 0.0), self.length)
        i = int(np.searchsorted(self.cumlen, s, side="right") - 1)
        i = min(i, len(self.points) - 2)
        seg = self.cumlen[i + 1] - self.cumlen[i]
        t = 0.0 if seg == 0 else (s - self.cumlen[i]) / seg
        return self.points[i] + t * (self.points[i + 1] - self.points[i])

    def at(self, s: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`point_at`: the points (k, 2) at arc lengths ``s`` (k,)."""
        return np.stack([np.interp(s, self.cumlen, self.points[:, 0]),
                         np.interp(s, self.cumlen, self.points[:, 1])], axis=-1)

    def heading_at(self, s: float) -> float:
        s = min(max(s, 0.0), self.length)
        i = int(np.searchsorted(self.cumlen, s, side="right") - 1)
        i = min(max(i, 0), len(self.points) - 2)
        d = self.points[i + 1] - self.points[i]
        return float(np.arctan2(d[1], d[0]))


class Raster:
    """A boolean grid over an axis-aligned box; cells are set by painting shapes."""

    def __init__(self, bounds: tuple[float, float, float, float], resolution: float = 0.25):
        self.xmin, self.ymin, xmax, ymax = bounds
        self.res = resolution
        self.nx = int(np.ceil((xmax - self.xmin) / resolution))
        self.ny = int(np.ceil((ymax - self.ymin) / resolution))
        self.grid = np.zeros((self.ny, self.nx), dtype=bool)

    def _window(self, lo: np.ndarray, hi: np.ndarray):
        i0 = max(int((lo[0] - self.xmin) / self.res), 0)
        j0 = max(int((lo[1] - self.ymin) / self.res), 0)
        i1 = min(int((hi[0] - self.xmin) / self.res) + 2, self.nx)
        j1 = min(int((hi[1] - self.ymin) / self.res) + 2, self.ny)
        if i0 >= i1 or j0 >= j1:
            return None
        xs = self.xmin + (np.arange(i0, i1) + 0.5) * self.res
        ys = self.ymin + (np.arange(j0, j1) + 0.5) * self.res
        gx, gy = np.meshgrid(xs, ys)
        return (slice(j0, j1), slice(i0, i1)), gx, gy

    def paint_polyline(self, points: np.ndarray, half_width: float) -> None:
        """Set every cell within half_width of the polyline (a lane of that width)."""
        pts = np.asarray(points, dtype=float)
        if len(pts) == 1:
            pts = np.vstack([pts, pts])
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            win = self._window(np.minimum(a, b) - half_width, np.maximum(a, b) + half_width)
            if win is None:
                continue
            sl, gx, gy = win
            d = b - a
            L2 = float(d @ d) or 1e-12
            t = np.clip(((gx - a[0]) * d[0] + (gy - a[1]) * d[1]) / L2, 0.0, 1.0)
            dist2 = (gx - a[0] - t * d[0]) ** 2 + (gy - a[1] - t * d[1]) ** 2
            self.grid[sl] |= dist2 <= half_width**2

    def paint_polygon(self, poly: np.ndarray) -> None:
        """Set every cell whose centre is inside the (possibly non-convex) polygon."""
        poly = np.asarray(poly, dtype=float)
        win = self._window(poly.min(axis=0), poly.max(axis=0))
        if win is None:
            return
        sl, gx, gy = win
        inside = np.zeros(gx.shape, dtype=bool)
        for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0), strict=True):
            crosses = (y0 > gy) != (y1 > gy)
            with np.errstate(divide="ignore", invalid="ignore"):
                xint = x0 + (gy - y0) * (x1 - x0) / (y1 - y0)
            inside ^= crosses & (gx < xint)
        self.grid[sl] |= inside

    def value_at(self, x: float, y: float) -> bool:
        """The value at one point (False outside the box); plain Python, for hot loops."""
        i = int((x - self.xmin) // self.res)
        j = int((y - self.ymin) // self.res)
        if 0 <= i < self.nx and 0 <= j < self.ny:
            return bool(self.grid[j, i])
        return False

    def lookup(self, points: np.ndarray) -> np.ndarray:
        """Values at points (k, 2); points outside the box read False."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        i = np.floor((pts[:, 0] - self.xmin) / self.res).astype(int)
        j = np.floor((pts[:, 1] - self.ymin) / self.res).astype(int)
        ok = (i >= 0) & (i < self.nx) & (j >= 0) & (j < self.ny)
        out = np.zeros(len(pts), dtype=bool)
        out[ok] = self.grid[j[ok], i[ok]]
        return out


WINDOW = 8  # segments searched either side of the cell's nearest one


class SegmentField:
    """For every cell near a polyline, the index of its nearest segment.

    Turns projection onto a long route into a grid lookup plus an exact projection
    onto three segments. Cells farther than `radius` fall back to the full search.
    """

    def __init__(self, path: Polyline, bounds, radius: float = 8.0, resolution: float = 0.5):
        self.path = path
        self.xmin, self.ymin, xmax, ymax = bounds
        self.res = resolution
        self.nx = int(np.ceil((xmax - self.xmin) / resolution))
        self.ny = int(np.ceil((ymax - self.ymin) / resolution))
        self.index = np.full((self.ny, self.nx), -1, dtype=np.int32)
        best = np.full((self.ny, self.nx), np.inf)
        for i, (a, b) in enumerate(zip(path.points[:-1], path.points[1:], strict=True)):
            lo, hi = np.minimum(a, b) - radius, np.maximum(a, b) + radius
            i0 = max(int((lo[0] - self.xmin) / resolution), 0)
            j0 = max(int((lo[1] - self.ymin) / resolution), 0)
            i1 = min(int((hi[0] - self.xmin) / resolution) + 2, self.nx)
            j1 = min(int((hi[1] - self.ymin) / resolution) + 2, self.ny)
            if i0 >= i1 or j0 >= j1:
                continue
            gx, gy = np.meshgrid(
                self.xmin + (np.arange(i0, i1) + 0.5) * resolution,
                self.ymin + (np.arange(j0, j1) + 0.5) * resolution,
            )
            d = b - a
            L2 = float(d @ d) or 1e-12
            t = np.clip(((gx - a[0]) * d[0] + (gy - a[1]) * d[1]) / L2, 0.0, 1.0)
            dist2 = (gx - a[0] - t * d[0]) ** 2 + (gy - a[1] - t * d[1]) ** 2
            win = best[j0:j1, i0:i1]
            closer = (dist2 < win) & (dist2 <= radius * radius)
            win[closer] = dist2[closer]
            self.index[j0:j1, i0:i1][closer] = i

    def project(self, x: float, y: float) -> float:
        """Arc length of the nearest point on the path (same answer as Polyline.project)."""
        i = int((x - self.xmin) // self.res)
        j = int((y - self.ymin) // self.res)
        seg = int(self.index[j, i]) if 0 <= i < self.nx and 0 <= j < self.ny else -1
        if seg < 0:
            return self.path.project(x, y)[0]
        pts, cum = self._pts, self._cum
        best_d, best_s = float("inf"), 0.0
        # a cell is 0.5 m wide but segments of junction lanes can be shorter: search around
        for k in range(max(seg - WINDOW, 0), min(seg + WINDOW, len(pts) - 2) + 1):
            ax, ay = pts[k]
            bx, by = pts[k + 1]
            dx, dy = bx - ax, by - ay
            L2 = dx * dx + dy * dy
            t = 0.0 if L2 == 0 else min(max(((x - ax) * dx + (y - ay) * dy) / L2, 0.0), 1.0)
            px, py = ax + t * dx - x, ay + t * dy - y
            d = px * px + py * py
            if d < best_d:
                best_d, best_s = d, cum[k] + t * L2**0.5
        return best_s

    @functools.cached_property
    def _pts(self) -> list[tuple[float, float]]:
        return [(float(x), float(y)) for x, y in self.path.points]

    @functools.cached_property
    def _cum(self) -> list[float]:
        return [float(c) for c in self.path.cumlen]
