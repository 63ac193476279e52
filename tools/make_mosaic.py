"""Make docs/camera_mosaic.png: what the six AC cameras of env_3 see, plus a top-down view.

Drives every AC with the Autopilot for ``--steps`` steps, syncs the PyBullet mirror
to the last snapshot and writes one PNG: the camera images in a grid (enlarged
with nearest neighbour so single pixels stay visible) beside a top-down view of
the region's centre. The defaults (seed 3, 40 steps after the 30 s traffic
warm-up) catch all six ACs driving, with pedestrians on the crossings; by step
150 two ACs have reached their goals and some cameras stare at the car queued
right ahead at the red light.

    python tools/make_mosaic.py [--scenario env_3] [--steps 40] [--seed 3] [--out docs/camera_mosaic.png]

``--route`` draws each AC's own route ahead into its camera (the ``route`` observation
variant, cosim.mirror.RouteBand); docs/route_cameras.png is

    python tools/make_mosaic.py --route --scenario env_2 --steps 25 --seed 3 --out docs/route_cameras.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cosim.controller import Autopilot
from cosim.mirror import ROUTE_AHEAD, ROUTE_SPACING, Mirror
from cosim.viz import mosaic, save_png, side_by_side
from cosim.world import World


def camera_mosaic(scenario: str = "env_3", steps: int = 40, seed: int = 3, cols: int = 3,
                  scale: int = 2, image_size: int = 84, extent: float | None = 100.0,
                  route: bool = False):
    """The mosaic image (uint8 H x W x 3) after `steps` Autopilot steps from `seed`.

    Cameras of ACs that already finished are taken at their last pose; `extent` is
    the width in metres of the top-down view (None: the whole region); `route`: each
    camera shows its own AC's route ahead, as with ``obs="route"``.
    """
    world = World(scenario)
    try:
        world.reset(seed=seed)
        pilots = {a: Autopilot(world, a) for a in world.ac_ids}
        for _ in range(steps):
            if not world.active:
                break
            world.step({a: tuple(pilots[a].act()) for a in world.active})
        poses = [world.ac_state(a)[:3] for a in world.ac_ids]
        routes = [world.route(a).ahead(x, y, ROUTE_AHEAD, ROUTE_SPACING)
                  for a, (x, y, _) in zip(world.ac_ids, poses, strict=True)] if route else None
        with Mirror(world.roadmap, image_size=image_size) as mirror:
            mirror.sync(world.snapshot)
            grid = mosaic(mirror.cameras(poses, routes), cols=cols, scale=scale)
            side = grid.shape[0]
            top = mirror.overview((side, side), extent=extent)
    finally:
        world.close()
    return side_by_side(grid, top)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="env_3")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--extent", type=float, default=100.0,
                    help="metres across the top-down view; 0 = the whole region")
    ap.add_argument("--out", type=Path, default=Path("docs/camera_mosaic.png"))
    ap.add_argument("--route", action="store_true", help="draw each AC's own route ahead (obs=route)")
    args = ap.parse_args()
    img = camera_mosaic(args.scenario, args.steps, args.seed, extent=args.extent or None,
                        route=args.route)
    path = save_png(args.out, img)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
