"""Full environment step with cameras: steps/s and AC-frames/s, a time breakdown, RSS over resets.

env_3 (four-way, background cars, pedestrians), 84x84 cameras, TinyRenderer on one
core. The ACs drive with the autopilot by default (its time is not counted: the
policy's cost is not the env's), so the cameras see what a car on the road sees;
``--policy forward`` is the old fixed half-throttle policy, which in the solid town
(docs/scenarios.md) parks most cars nose-first against a wall that fills their
camera. ``--no-solid`` drops the walls and the island for an A/B comparison.
Prints a Markdown table; medians of --repeats runs.

    python bench/env_step.py [--steps 600] [--repeats 3] [--resets 200] [--policy forward] [--no-solid]
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


def run(n: int, steps: int, seed: int, policy: str = "autopilot", solid: bool = True) -> dict:
    env = cosim.parallel_env(scenario(solid), num_agents=n, action_types="continuous",
                             terminate_on_collision=False, seed=seed)
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
    args = parser.parse_args()
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
    rss = resets(args.resets)
    print(f"\nRSS over {args.resets} resets (6 ACs): after 1: {rss[0]:.0f} MB, after 20: "
          f"{rss[min(19, len(rss) - 1)]:.0f} MB, after {len(rss)}: {rss[-1]:.0f} MB "
          f"(growth from 20 to {len(rss)}: {rss[-1] - rss[min(19, len(rss) - 1)]:+.1f} MB)")


if __name__ == "__main__":
    main()
