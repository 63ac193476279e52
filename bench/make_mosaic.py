"""Make docs/camera_mosaic.png: what the six AC cameras of env_3 see, plus a top-down view.

Drives every AC with the Autopilot for ``--steps`` steps, syncs the PyBullet mirror
to the last snapshot and writes one PNG: the camera images in a grid (enlarged
with nearest neighbour so single pixels stay visible) beside the overview.

    python bench/make_mosaic.py [--scenario env_3] [--steps 150] [--out docs/camera_mosaic.png]
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from cosim.controller import Autopilot
from cosim.mirror import Mirror
from cosim.viz import mosaic, save_png, side_by_side
from cosim.world import World

log = logging.getLogger(__name__)


def camera_mosaic(scenario: str = "env_3", steps: int = 150, seed: int = 1, cols: int = 3,
                  scale: int = 2, image_size: int = 84):
    """The mosaic image (uint8 H x W x 3) after `steps` Autopilot steps from `seed`."""
    world = World(scenario)
    try:
        world.reset(seed=seed)
        pilots = {a: Autopilot(world, a) for a in world.ac_ids}
        for _ in range(steps):
            if not world.active:
                break
            world.step({a: tuple(pilots[a].act()) for a in world.active})
        acs = world.active or world.ac_ids
        poses = [world.ac_state(a)[:3] for a in acs]
        with Mirror(world.roadmap, image_size=image_size) as mirror:
            mirror.sync(world.snapshot)
            grid = mosaic(mirror.cameras(poses), cols=cols, scale=scale)
            side = grid.shape[0]
            top = mirror.overview((side, side))
    finally:
        world.close()
    return side_by_side(grid, top)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="env_3")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("docs/camera_mosaic.png"))
    args = ap.parse_args()
    path = save_png(args.out, camera_mosaic(args.scenario, args.steps, args.seed))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
