"""Wall time of the smoke benchmark grid on Ray Tune with 1 and 2 concurrent trials, and
without Ray (one trial after another in one process), and the speedup.

Each row runs `cosim benchmark --preset smoke --train-only` as a user would (a
fresh process: Ray start-up and shutdown included) into its own folder; the
test protocol and report that follow training are timed once, separately.

    python bench/benchmark_smoke.py [--envs env_1 env_2] [--algos ppo dqn ...] [--report]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from agents.registry import ALGORITHMS
from cosim.scenario import available_scenarios


def timed(args: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "eval.cli", *args], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    return time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", nargs="+", default=available_scenarios())
    p.add_argument("--algos", nargs="+", default=list(ALGORITHMS))
    p.add_argument("--report", action="store_true", help="also time the test protocol and report")
    p.add_argument("--out", type=Path, default=None, help="also write the figures as JSON")
    args = p.parse_args()
    grid = ["benchmark", "--preset", "smoke", "--envs", *args.envs, "--algos", *args.algos,
            "--quiet"]
    trials = len(args.envs) * len(args.algos)
    rows = {}
    with tempfile.TemporaryDirectory(prefix="bsmoke") as tmp:
        for label, extra in (("no Ray", ["--no-ray"]), ("Ray, 1 concurrent", ["--concurrent", "1"]),
                             ("Ray, 2 concurrent", ["--concurrent", "2"])):
            out = Path(tmp) / label.replace(" ", "").replace(",", "")
            rows[label] = timed([*grid, "--train-only", *extra, "--out", str(out)])
            print(f"{label:20s} {trials} trials: {rows[label]:7.1f} s", flush=True)
        if args.report:  # the test and report of the last grid, on its trained folders
            out = Path(tmp) / "report"
            rows["train + test + report (Ray, 2)"] = timed([*grid, "--concurrent", "2", "--out", str(out)])
            print(f"train + test + report (Ray, 2): {rows['train + test + report (Ray, 2)']:.1f} s")
    speedup = rows["Ray, 1 concurrent"] / rows["Ray, 2 concurrent"]
    print(f"speedup 2 vs 1 concurrent: {speedup:.2f}x; Ray(2) vs no Ray: "
          f"{rows['no Ray'] / rows['Ray, 2 concurrent']:.2f}x "
          f"(cores {os.cpu_count()}, load average {os.getloadavg()[0]:.1f} at the end)")
    if args.out:
        args.out.write_text(json.dumps({"trials": trials, "seconds": rows, "speedup": speedup,
                                        "envs": args.envs, "algos": args.algos}, indent=2))


if __name__ == "__main__":
    main()
