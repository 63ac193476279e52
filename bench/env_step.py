"""Full environment step with cameras: steps/s and AC-frames/s, a time breakdown, RSS over resets.

env_3 (four-way, background cars, pedestrians), 84x84 cameras, TinyRenderer on one
core. The ACs drive with the autopilot by default (its time is not counted: the
policy's cost is not the env's), so the cameras see what a car on the road sees;
``--policy forward`` is the old fixed half-throttle policy, which in the solid town
(docs/scenarios.md) parks most cars nose-first against a wall that fills their
camera. ``--no-solid`` drops the walls and the island for an A/B comparison.
Prints a Markdown table; medians of --repeats runs. ``--obs route`` is an A/B of the route
camera (each AC's route ahead drawn into its frame, docs/task.md "The route variant") against
the plain camera: the two alternate run by run (same seeds), so a background load hits both.

    python bench/env_step.py [--steps 600] [--repeats 3] [--resets 200] [--policy forward] [--no-solid]
    python bench/env_step.py --obs route [--steps 600] [--repeats 5] [--resets 0]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time

import numpy as np

import cosim
from cosim.controller import Autopilot
from cosim.scenario import load_scenario


def rss_mb() -> float:
    with open(f"/proc/{os.getpid()}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def scenario(solid: bool):
    sc = load_scenario("env_3")
    if solid:
        return sc
    return dataclasses.replace(sc, additional=tuple(p for p in sc.additional
                                                    if p.name != "solid.add.xml"))


def run(n: int, steps: int, seed: int, policy: str = "autopilot", solid: bool = True,
        obs: str = "image") -> dict:
    env = cosim.parallel_env(scenario(solid), num_agents=n, action_types="continuous",
                             terminate_on_collision=False, seed=seed, obs=obs)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    w = env.world
    pilots = {a: Autopilot(w, a) for a in env.agents}
    phases = dict.fromkeys(["dynamics", "sumo", "snapshot", "events", "mirror_sync", "render"], 0.0)
    elapsed, done, frames = 0.0, 0, 0
    while done < steps:
        if not env.agents:
            for k in ("dynamics", "sumo", "snapshot", "events"):
                phases[k] += getattr(w.times, k)
            env.reset(seed=seed + done)
            pilots = {a: Autopilot(w, a) for a in env.agents}
        if policy == "autopilot":
            actions = {a: pilots[a].act() for a in env.agents}
        else:
            actions = {a: np.array([0.5, rng.normal(0, 0.05)], np.float32) for a in env.agents}
        frames += len(env.agents)
        t0 = time.perf_counter()
        env.step(actions)
        elapsed += time.perf_counter() - t0
        done += 1
    for k in ("dynamics", "sumo", "snapshot", "events"):
        phases[k] += getattr(w.times, k)
    phases["mirror_sync"] = env.timings["mirror_sync"]
    phases["render"] = env.timings["render"]
    triangles = env.mirror.triangle_count
    env.close()
    return {"steps_per_s": steps / elapsed, "frames_per_s": frames / elapsed,
            "ms": {k: 1e3 * v / steps for k, v in phases.items()}, "triangles": triangles}


def resets(count: int) -> list[float]:
    env = cosim.parallel_env("env_3", num_agents=6, horizon=5)
    out = []
    for i in range(count):
        env.reset(seed=i)
        while env.agents:
            env.step({a: 3 for a in env.agents})
        out.append(rss_mb())
    env.close()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--resets", type=int, default=200)
    parser.add_argument("--policy", choices=["autopilot", "forward"], default="autopilot")
    parser.add_argument("--no-solid", action="store_true", help="without walls and island")
    parser.add_argument("--obs", choices=["image", "route"], default="image",
                        help="route: A/B of the route camera against the plain one")
    args = parser.parse_args()
    if args.obs == "route":
        route_ab(args)
        return
    print("| ACs | env steps/s | AC-frames/s | dynamics+moveToXY | SUMO | snapshot | events+reward "
          "| mirror sync | render | triangles |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for n in (1, 3, 6):
        runs = [run(n, args.steps, 20 + r, args.policy, not args.no_solid)
                for r in range(args.repeats)]
        med = sorted(runs, key=lambda r: r["steps_per_s"])[len(runs) // 2]
        ms = med["ms"]
        print(f"| {n} | {statistics.median(r['steps_per_s'] for r in runs):.0f} | "
              f"{statistics.median(r['frames_per_s'] for r in runs):.0f} | "
              + " | ".join(f"{ms[k]:.2f} ms" for k in
                           ("dynamics", "sumo", "snapshot", "events", "mirror_sync", "render"))
              + f" | {med['triangles']} |")
    if args.resets > 0:
        report_resets(args.resets)


def route_ab(args) -> None:
    """The step rate with and without the route drawn, runs alternating (image, route) with the
    same seed; the ratio is the median of the pairs' ratios."""
    print("| ACs | image: env steps/s | route: env steps/s | route / image (median of pairs) | "
          "image: render ms | route: render ms |")
    print("|---|---|---|---|---|---|")
    overheads = []
    for n in (1, 3, 6):
        runs = {"image": [], "route": []}
        for r in range(args.repeats):
            for obs in runs:
                runs[obs].append(run(n, args.steps, 20 + r, args.policy, not args.no_solid, obs))
        rate = {o: statistics.median(x["steps_per_s"] for x in v) for o, v in runs.items()}
        render = {o: statistics.median(x["ms"]["render"] for x in v) for o, v in runs.items()}
        pairs = statistics.median(b["steps_per_s"] / a["steps_per_s"]
                                  for a, b in zip(runs["image"], runs["route"], strict=True))
        print(f"| {n} | {rate['image']:.1f} | {rate['route']:.1f} | {pairs:.3f} | "
              f"{render['image']:.2f} | {render['route']:.2f} |")
        extra = route_overhead(n, args.steps, 20)
        step_ms = 1e3 / rate["image"]
        overheads.append(f"| {n} | {extra:.3f} | {step_ms:.2f} | {step_ms / (step_ms + extra):.3f} |")
    print("\nThe route's own cost, timed in one process: each step the same cameras rendered without "
          "and with the routes, alternating (median of the steps):\n")
    print("| ACs | route ms per step | image step ms (above) | image step / (image step + route) |")
    print("|---|---|---|---|")
    print("\n".join(overheads))
    if args.resets > 0:
        report_resets(args.resets)


def route_overhead(n: int, steps: int, seed: int) -> float:
    """Median ms per step the route adds to the cameras: the same poses rendered with and
    without each AC's route ahead (Route.ahead included), one after the other in alternating
    order, every step of an autopilot drive."""
    env = cosim.parallel_env("env_3", num_agents=n, action_types="continuous", seed=seed, obs="route")
    env.reset(seed=seed)
    pilots = {a: Autopilot(env.world, a) for a in env.agents}
    extra = []
    for _ in range(steps):
        if not env.agents:
            env.reset(seed=seed + len(extra))
            pilots = {a: Autopilot(env.world, a) for a in env.agents}
        env.step({a: pilots[a].act() for a in env.agents})
        poses = [env.world.ac_state(a)[:3] for a in env.agents]
        if not poses:
            continue
        took = {}
        for routes in ((False, True) if len(extra) % 2 else (True, False)):  # either order in turn
            t0 = time.perf_counter()
            env.mirror.cameras(poses, env._routes_ahead(env.agents, poses) if routes else None)
            took[routes] = time.perf_counter() - t0
        extra.append(took[True] - took[False])
    env.close()
    return 1e3 * statistics.median(extra)


def report_resets(count: int) -> None:
    rss = resets(count)
    print(f"\nRSS over {count} resets (6 ACs): after 1: {rss[0]:.0f} MB, after 20: "
          f"{rss[min(19, len(rss) - 1)]:.0f} MB, after {len(rss)}: {rss[-1]:.0f} MB "
          f"(growth from 20 to {len(rss)}: {rss[-1] - rss[min(19, len(rss) - 1)]:+.1f} MB)")


if __name__ == "__main__":
    main()
