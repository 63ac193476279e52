"""Memory kept by environments created and closed in one process (issue 10, item 4).

Creates, resets (which starts SUMO and builds the PyBullet mirror), steps once and
closes ``--envs`` environments one after another in this process, and prints the
resident set size (RSS) after the warm-up environments and after the last one, and
the median growth per environment. Anything an environment keeps after ``close()``
shows up as steady growth; allocator noise does not move the median. A second row
runs the same number of bare ``libsumo.start`` / ``simulationStep`` / ``close`` with
the environment's own SUMO command and nothing of cosim around it: what SUMO itself
keeps per start, which cosim cannot free (reloading one simulation with
``libsumo.load``, what ``reset`` does, keeps ~4 kB per reload).

    python bench/env_memory.py [--envs 200] [--warmup 5] [--scenario env_1] [--json]

``--json`` prints one JSON object instead of the table (tests/cosim/test_env_memory.py
runs it that way, in a fresh process).
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import os
import statistics

import cosim


def _malloc_trim() -> None:
    """Hand freed heap memory back to the OS (glibc), so RSS counts live memory only.

    Without it, a freed ~45 MB block (the ground raster of the previous mirror) may
    stay in the heap or not, and RSS jumps by that much either way between runs.
    """
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: RSS includes the allocator's free pages
        pass


def rss_mb() -> float:
    """This process's resident set size in MB (Linux ``/proc``), after a GC and malloc_trim."""
    gc.collect()
    _malloc_trim()
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def one_env(scenario: str, seed: int) -> None:
    env = cosim.parallel_env(scenario, num_agents=1, background=False, pedestrians=False)
    env.reset(seed=seed)
    env.step({a: 0 for a in env.agents})
    env.close()


def one_libsumo(command: list[str]) -> None:
    import libsumo

    libsumo.start(command)
    libsumo.simulationStep()
    libsumo.close()


def measure(envs: int, warmup: int, scenario: str, what: str = "env") -> dict:
    """RSS before (after ``warmup`` environments) and after ``envs`` more; growth per env."""
    if what == "env":
        def one(k):
            one_env(scenario, k)
    else:  # "libsumo": the same SUMO command, started and closed bare
        env = cosim.parallel_env(scenario, num_agents=1, background=False, pedestrians=False)
        command = env.world.bridge.command(0)
        env.close()

        def one(k):
            one_libsumo(command)
    for k in range(warmup):
        one(k)
    before = last = rss_mb()
    per_env = []
    for k in range(envs):
        one(warmup + k)
        now = rss_mb()
        per_env.append(now - last)
        last = now
    return {"what": what, "scenario": scenario, "envs": envs, "warmup": warmup, "rss_before_mb": before,
            "rss_after_mb": last, "growth_mb": last - before,
            "median_per_env_mb": statistics.median(per_env),
            "mean_per_env_mb": (last - before) / envs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=200)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--scenario", default="env_1")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--no-libsumo-row", action="store_true",
                        help="skip the bare libsumo start/close row")
    args = parser.parse_args()
    r = measure(args.envs, args.warmup, args.scenario)
    if args.json:
        print(json.dumps(r))
        return
    rows = [r] if args.no_libsumo_row else [
        r, measure(args.envs, args.warmup, args.scenario, what="libsumo")]
    print("| created and closed | scenario | n | RSS before | RSS after | growth | "
          "median per env | mean per env |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        what = "environment (SUMO + mirror)" if r["what"] == "env" else "bare libsumo start/close"
        print(f"| {what} | {r['scenario']} | {r['envs']} | {r['rss_before_mb']:.1f} MB | "
              f"{r['rss_after_mb']:.1f} MB | {r['growth_mb']:+.1f} MB | "
              f"{1e3 * r['median_per_env_mb']:.0f} kB | {1e3 * r['mean_per_env_mb']:.0f} kB |")


if __name__ == "__main__":
    main()
