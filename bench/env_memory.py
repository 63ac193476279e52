"""Memory kept by environments created and closed in one process (issue 10, item 4).

Creates, resets (which starts SUMO and builds the PyBullet mirror), steps once and
closes ``--envs`` environments one after another in this process, and prints the
resident set size (RSS) after the warm-up environments and after the last one, and
the median growth per environment. Anything an environment keeps after ``close()``
shows up as steady growth; allocator noise does not move the median.

    python bench/env_memory.py [--envs 200] [--warmup 5] [--scenario env_1] [--json]

``--json`` prints one JSON object instead of the table (tests/cosim/test_env_memory.py
runs it that way, in a fresh process).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics

import cosim


def rss_mb() -> float:
    """This process's resident set size in MB (Linux ``/proc``)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def one_env(scenario: str, seed: int) -> None:
    env = cosim.parallel_env(scenario, num_agents=1, background=False, pedestrians=False)
    env.reset(seed=seed)
    env.step({a: 0 for a in env.agents})
    env.close()


def measure(envs: int, warmup: int, scenario: str) -> dict:
    """RSS before (after ``warmup`` environments) and after ``envs`` more; growth per env."""
    for k in range(warmup):
        one_env(scenario, k)
    gc.collect()
    before = last = rss_mb()
    per_env = []
    for k in range(envs):
        one_env(scenario, warmup + k)
        gc.collect()
        now = rss_mb()
        per_env.append(now - last)
        last = now
    return {"scenario": scenario, "envs": envs, "warmup": warmup, "rss_before_mb": before,
            "rss_after_mb": last, "growth_mb": last - before,
            "median_per_env_mb": statistics.median(per_env),
            "mean_per_env_mb": (last - before) / envs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=200)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--scenario", default="env_1")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    r = measure(args.envs, args.warmup, args.scenario)
    if args.json:
        print(json.dumps(r))
        return
    print("| scenario | envs | RSS before | RSS after | growth | median per env | mean per env |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {r['scenario']} | {r['envs']} | {r['rss_before_mb']:.1f} MB | "
          f"{r['rss_after_mb']:.1f} MB | {r['growth_mb']:+.1f} MB | "
          f"{1e3 * r['median_per_env_mb']:.0f} kB | {1e3 * r['mean_per_env_mb']:.0f} kB |")


if __name__ == "__main__":
    main()
