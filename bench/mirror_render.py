"""Benchmark: how fast the PyBullet mirror renders the AC cameras (TinyRenderer, CPU).

Drives env_3 with the Autopilot for a while so the pool holds real traffic, then
times ``Mirror.cameras`` for 1, 3 and 6 ACs and ``Mirror.sync``. Each figure is the
median over repeated batches; CPU time of this process is reported next to wall
time because the wall clock on a shared machine includes other people's work.

    python bench/mirror_render.py [--scenario env_3] [--size 84] [--steps 150] [--ground-meshes]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from cosim.controller import Autopilot
from cosim.mirror import Mirror
from cosim.world import World


def timed(fn, calls: int, repeats: int) -> tuple[float, float]:
    """Median (wall, cpu) seconds per call over `repeats` batches of `calls` calls."""
    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        for _ in range(calls):
            fn()
        wall.append((time.perf_counter() - w0) / calls)
        cpu.append((time.process_time() - c0) / calls)
    return statistics.median(wall), statistics.median(cpu)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="env_3")
    ap.add_argument("--size", type=int, default=84)
    ap.add_argument("--steps", type=int, default=150, help="Autopilot steps before timing")
    ap.add_argument("--calls", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    ap.add_argument("--ground-meshes", action="store_true",
                    help="for comparison: TinyRenderer draws road/sidewalk/marking meshes "
                         "instead of the GroundRaster")
    args = ap.parse_args()

    world = World(args.scenario)
    world.reset(seed=1)
    pilots = {a: Autopilot(world, a) for a in world.ac_ids}
    for _ in range(args.steps):
        if not world.active:
            break
        world.step({a: tuple(pilots[a].act()) for a in world.active})
    snapshot = world.snapshot
    poses = [world.ac_state(a)[:3] for a in world.ac_ids]
    t0 = time.perf_counter()
    mirror = Mirror(world.roadmap, image_size=args.size)
    build_s = time.perf_counter() - t0
    try:
        if args.ground_meshes:
            mirror._ground = None  # private switch, for this comparison only
            mirror._show_ground_meshes(True)
        mirror.sync(snapshot)
        sync_wall, sync_cpu = timed(lambda: mirror.sync(snapshot), args.calls, args.repeats)
        rows = []
        for n in (1, 3, 6):
            ps = [poses[i % len(poses)] for i in range(n)]
            wall, cpu = timed(lambda ps=ps: mirror.cameras(ps), args.calls, args.repeats)
            rows.append({"acs": n, "ms_per_call_wall": 1e3 * wall, "ms_per_call_cpu": 1e3 * cpu,
                         "ms_per_frame_cpu": 1e3 * cpu / n, "frames_per_s_cpu": n / cpu,
                         "frames_per_s_wall": n / wall})
        result = {
            "scenario": args.scenario, "image_size": args.size,
            "triangles_total": mirror.triangle_count,
            "triangles_static": mirror._static_triangles,
            # road, sidewalk and marking meshes are hidden from TinyRenderer (GroundRaster)
            "triangles_static_tiny": mirror._static_triangles - (
                0 if args.ground_meshes else mirror._ground_triangles),
            "ground_raster_mb": mirror._ground.nbytes / 1e6 if mirror._ground else 0.0,
            "build_s": build_s,
            "cars_in_view": int(len(snapshot.vehicle_ids)),
            "pedestrians": int(len(snapshot.person_ids)),
            "sync_ms_wall": 1e3 * sync_wall, "sync_ms_cpu": 1e3 * sync_cpu,
            "cameras": rows,
            "image_mean": float(np.mean(mirror.cameras(poses))),
        }
    finally:
        mirror.close()
        world.close()
    if args.json:
        print(json.dumps(result, indent=1))
        return
    print(f"{args.scenario} {args.size}x{args.size}: {result['triangles_total']} triangles "
          f"({result['triangles_static']} static, of which TinyRenderer draws "
          f"{result['triangles_static_tiny']}; ground raster {result['ground_raster_mb']:.1f} MB), "
          f"{result['cars_in_view']} cars, {result['pedestrians']} pedestrians; "
          f"sync {result['sync_ms_cpu']:.3f} ms CPU; built in {result['build_s']:.2f} s")
    print("| ACs | ms per cameras() call (CPU) | ms per frame (CPU) | frames/s (CPU) | "
          "ms per call (wall) |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['acs']} | {r['ms_per_call_cpu']:.2f} | {r['ms_per_frame_cpu']:.2f} | "
              f"{r['frames_per_s_cpu']:.0f} | {r['ms_per_call_wall']:.2f} |")


if __name__ == "__main__":
    main()
