"""Generate the solid town: walls along the roads and the roundabout's island.

    python tools/make_solid_town.py            # writes sumo_nets/town/solid.add.xml

Why (docs/scenarios.md, "A solid town"): a car that leaves the road must soon hit
something, as in a real town, so that no open-loop policy reaches a goal by driving
across open ground. The rules, applied to every road of the network:

- a road side with a sidewalk gets a wall just beyond the sidewalk (the building
  line); walls are extended at their ends until they meet another wall or come
  close to a carriageway, so junction corners are closed;
- a road side with neither a sidewalk nor an opposite carriageway (the ramp, the
  ring's outside, the merge road) gets a wall on its verge, 1 m from the lane edge,
  unless an object is already there (the merge's guard rails);
- the roundabout's island is a raised, planted kerb (kind ``island``) with a
  monument (kind ``building``) at its centre.

Wall pieces that would touch a carriageway (junction paths included) or a sidewalk
are dropped,
so every entry and exit stays open. The output is plain SUMO ``<poly>`` data:
edit it in netedit or re-run this script after changing the network.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from cosim.geometry import Raster
from cosim.roadmap import read_net, read_objects
from cosim.scenario import nets_dir

WALL_THICKNESS = 0.4  # metres
WALL_GAP = 0.3  # metres between a sidewalk's outer edge and the wall
VERGE = 1.0  # metres between a lane edge and a verge wall (no sidewalk)
CLEARANCE = 0.6  # metres a wall keeps from any carriageway, junction or sidewalk
PIECE = 8.0  # metres: walls are laid (and checked for clearance) in pieces this long
MERGED = 60.0  # metres: collinear pieces are then joined into boxes up to this long
EXTEND = 15.0  # metres a wall may be extended at each end to close a corner
ISLAND_CLEARANCE = 1.5  # metres between the ring lane's inner edge and the island kerb
MONUMENT_RADIUS = 3.0


def offset_polyline(points: np.ndarray, distance: float) -> np.ndarray:
    """The polyline shifted sideways by `distance` (positive = to the right of travel)."""
    pts = np.asarray(points, dtype=float)[:, :2]
    d = np.diff(pts, axis=0)
    n = np.stack([d[:, 1], -d[:, 0]], axis=1)  # right-hand normals
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    normals = np.zeros_like(pts)
    normals[:-1] += n
    normals[1:] += n
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return pts + normals * distance


def cut(points: np.ndarray, piece: float = PIECE) -> list[tuple[np.ndarray, np.ndarray]]:
    """Split a polyline into straight pieces of at most `piece` metres."""
    out = []
    for a, b in zip(points[:-1], points[1:], strict=True):
        length = float(np.hypot(*(b - a)))
        if length < 1e-6:
            continue
        k = max(1, math.ceil(length / piece))
        for i in range(k):
            out.append((a + (b - a) * i / k, a + (b - a) * (i + 1) / k))
    return out


def merge(pieces: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Join consecutive collinear pieces (up to MERGED metres): the same wall in fewer
    boxes, so the cameras draw fewer triangles (TinyRenderer pays per triangle)."""
    out: list[tuple[np.ndarray, np.ndarray]] = []
    for a, b in pieces:
        if out:
            pa, pb = out[-1]
            d0, d1 = (pb - pa) / np.hypot(*(pb - pa)), (b - a) / np.hypot(*(b - a))
            joined = np.hypot(*(pb - a)) < 1e-6 and float(d0 @ d1) > math.cos(math.radians(1.0))
            if joined and np.hypot(*(b - pa)) <= MERGED:
                out[-1] = (pa, b)
                continue
        out.append((a, b))
    return out


def rectangle(a: np.ndarray, b: np.ndarray, thickness: float = WALL_THICKNESS) -> np.ndarray:
    d = (b - a) / np.hypot(*(b - a))
    n = np.array([-d[1], d[0]]) * thickness / 2
    return np.array([a - n, b - n, b + n, a + n])


def regular_polygon(centre, radius: float, sides: int) -> np.ndarray:
    t = np.linspace(0, 2 * math.pi, sides, endpoint=False)
    return np.stack([centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)], axis=1)


class Town:
    """The network's surfaces a wall must keep clear of, as a raster."""

    def __init__(self, net, existing: list[np.ndarray]):
        self.net = net
        xmin, ymin, xmax, ymax = (float(v) for v in np.ravel(net.getBBoxXY()))
        self.bounds = (xmin - 40, ymin - 40, xmax + 40, ymax + 40)
        self.clear = Raster(self.bounds, 0.2)
        for edge in net.getEdges(withInternal=True):
            if edge.getFunction() in ("walkingarea", "crossing"):
                continue  # a wall may cross a walking area's outer corner, never the road
            for lane in edge.getLanes():
                if edge.getFunction() == "internal" and not lane.allows("passenger"):
                    continue
                # carriageways keep CLEARANCE; a wall may stand close to a sidewalk's edge
                margin = CLEARANCE if lane.allows("passenger") else WALL_GAP / 2
                self.clear.paint_polyline(np.asarray(lane.getShape())[:, :2],
                                          lane.getWidth() / 2 + margin)
        self.existing = Raster(self.bounds, 0.2)  # objects placed by hand
        for poly in existing:
            self.existing.paint_polygon(poly)
            self.existing.paint_polyline(np.vstack([poly, poly[:1]]), 0.3)
        self.walls = Raster(self.bounds, 0.2)  # walls placed so far

    def free(self, a: np.ndarray, b: np.ndarray, walls: bool = False) -> bool:
        """Whether a wall piece from a to b touches nothing it must keep clear of."""
        d = (b - a) / np.hypot(*(b - a))
        n = np.array([-d[1], d[0]]) * WALL_THICKNESS / 2
        t = np.linspace(0, 1, max(2, int(np.hypot(*(b - a)) / 0.2) + 1))[:, None]
        line = a + (b - a) * t
        samples = np.concatenate([line - n, line, line + n])
        blocked = self.clear.lookup(samples).any() or self.existing.lookup(samples).any()
        return not (blocked or (walls and self.walls.lookup(samples).any()))

    def place(self, a: np.ndarray, b: np.ndarray) -> None:
        self.walls.paint_polygon(rectangle(a, b, WALL_THICKNESS + 0.2))


def wall_lines(net) -> list[np.ndarray]:
    """Centre lines of the walls beside every road (see the module docstring)."""
    lines = []
    ring = {e for r in net.getRoundabouts() for e in r.getEdges()}
    for edge in net.getEdges(withInternal=False):
        lanes = edge.getLanes()
        cars = [ln for ln in lanes if ln.allows("passenger")]
        if not cars:
            continue
        walk = lanes[0] if not lanes[0].allows("passenger") and lanes[0].allows("pedestrian") else None
        if walk is not None:
            lines.append(offset_polyline(walk.getShape(),
                                         walk.getWidth() / 2 + WALL_GAP + WALL_THICKNESS / 2))
        else:
            right = cars[0]
            lines.append(offset_polyline(right.getShape(), right.getWidth() / 2 + VERGE))
        reverse = any(e.getToNode() == edge.getFromNode() for e in edge.getToNode().getOutgoing())
        if not reverse and edge.getID() not in ring:
            left = cars[-1]
            lines.append(offset_polyline(left.getShape(), -(left.getWidth() / 2 + VERGE)))
    return lines


def extend(town: Town, a: np.ndarray, b: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pieces continuing the wall beyond b (direction a -> b) until it meets something."""
    d = (b - a) / np.hypot(*(b - a))
    out, start, step = [], b, 0.5
    for _ in range(int(EXTEND / step)):
        end = start + d * step
        if not town.free(start + d * 0.3, end, walls=True):
            break
        out.append((start, end))
        start = end
    if not out:
        return []
    return [(out[0][0], out[-1][1])]


def build(net_path: Path, objects_path: Path) -> list[tuple[str, str, np.ndarray]]:
    net = read_net(net_path)
    existing = [o.polygon for o in read_objects(objects_path)]
    town = Town(net, existing)
    polys: list[tuple[str, str, np.ndarray]] = []

    for r in net.getRoundabouts():
        shapes = [np.asarray(net.getEdge(e).getLanes()[0].getShape())[:, :2]
                  for e in r.getEdges()]
        ring_pts = np.concatenate(shapes)
        centre = ring_pts.mean(axis=0)
        width = net.getEdge(r.getEdges()[0]).getLanes()[0].getWidth()
        inner = float(np.min(np.hypot(*(ring_pts - centre).T))) - width / 2
        island = regular_polygon(centre, inner - ISLAND_CLEARANCE, 24)
        polys.append((f"island_{len(polys)}", "island", island))
        polys.append((f"monument_{len(polys)}", "building",
                      regular_polygon(centre, MONUMENT_RADIUS, 8)))
        town.existing.paint_polygon(island)

    pieces = []
    for line in wall_lines(net):
        kept = merge([(a, b) for a, b in cut(line) if town.free(a, b)])
        for a, b in kept:
            town.place(a, b)
        pieces.append(kept)
    # close the corners: continue each wall's first and last piece until it meets something
    for kept in pieces:
        if not kept:
            continue
        extra = extend(town, *kept[-1]) + [(b, a) for a, b in extend(town, kept[0][1], kept[0][0])]
        for a, b in extra:
            town.place(a, b)
        kept.extend(extra)
    for kept in pieces:
        for a, b in kept:
            polys.append((f"wall_{len(polys)}", "wall", rectangle(a, b)))
    return polys


COLOURS = {"wall": "0.55,0.32,0.26", "island": "0.25,0.50,0.22", "building": "0.72,0.52,0.40"}


def write(polys, out: Path) -> None:
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        "<!-- The solid town: walls along the roads and the roundabout island (CO objects).",
        "     Generated by tools/make_solid_town.py; see docs/scenarios.md. -->",
        "<additional>",
    ]
    for pid, kind, poly in polys:
        shape = " ".join(f"{x:.2f},{y:.2f}" for x, y in poly)
        lines.append(f'    <poly id="{pid}" type="{kind}" color="{COLOURS[kind]}" fill="1" '
                     f'layer="1" shape="{shape}"/>')
    lines.append("</additional>")
    out.write_text("\n".join(lines) + "\n")


def main() -> None:
    town = nets_dir() / "town"
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--net", type=Path, default=town / "town.net.xml")
    p.add_argument("--objects", type=Path, default=town / "objects.add.xml",
                   help="objects already placed by hand (walls keep clear of them)")
    p.add_argument("--out", type=Path, default=town / "solid.add.xml")
    args = p.parse_args()
    polys = build(args.net, args.objects)
    write(polys, args.out)
    kinds = {k: sum(1 for _, kk, _ in polys if kk == k) for k in COLOURS}
    print(f"wrote {args.out}: {kinds}")


if __name__ == "__main__":
    main()
