"""Disk a user pays: the smoke benchmark's folder and one run folder per algorithm at a preset.

Runs what a user runs, as a fresh process, into a temporary folder, and measures the
bytes on disk (``du``-style: every file's size) by part:

    python bench/disk.py                         # smoke benchmark + quick runs, --keep best
    python bench/disk.py --keep all              # what a finished run keeps with --keep all
    python bench/disk.py --skip-benchmark        # the run folders only (a few minutes)

Run folders: ``cosim train --algo all --preset PRESET --steps S`` (6 ACs at quick). The
checkpoint files do not depend on the step count; the logs that grow with it
(episodes.csv, TensorBoard) are measured per env step and extrapolated to the preset's
own budget for that algorithm (printed beside the measured size).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

MB = 1e6


def size(path: Path) -> int:
    """Bytes of every file under ``path`` (0 when absent)."""
    path = Path(path)
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def cosim(args: list[str]) -> float:
    """Run ``cosim ARGS`` as a user would; return its wall time."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "eval.cli", *args], stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        sys.exit(f"cosim {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return time.perf_counter() - start


def run_folders(tmp: Path, preset: str, steps: int, keep: str) -> dict[str, dict[str, float]]:
    from eval.training.presets import load_presets

    budget = load_presets()[preset].steps
    cosim(["train", "--algo", "all", "--preset", preset, "--steps", str(steps), "--keep", keep,
           "--out", str(tmp / "runs")])
    rows = {}
    for run in sorted((tmp / "runs").iterdir()):
        algo = run.name.split("__")[1]
        ckpt = size(run / "checkpoints")
        logs = size(run) - ckpt
        growing = size(run / "tb") + size(run / "episodes.csv")  # the rest is fixed (config, plot)
        full_logs = logs + growing * (budget[algo] / steps - 1)
        rows[algo] = {"acs": len(list((run / "checkpoints").iterdir())), "checkpoints_mb": ckpt / MB,
                      "logs_mb": logs / MB, "total_mb": size(run) / MB, "budget_steps": budget[algo],
                      "total_at_budget_mb": (ckpt + full_logs) / MB}
        print(f"{algo:7s} {rows[algo]['acs']} ACs  checkpoints {ckpt / MB:6.1f} MB  logs {logs / MB:5.2f} MB"
              f"  run folder {size(run) / MB:6.1f} MB  (at its {preset} budget of {budget[algo]} steps: "
              f"~{rows[algo]['total_at_budget_mb']:.1f} MB)", flush=True)
    return rows


def benchmark(tmp: Path, keep: str) -> dict[str, float]:
    out = tmp / "bench"
    seconds = cosim(["benchmark", "--preset", "smoke", "--keep", keep, "--quiet", "--out", str(out)])
    parts = {p.name: size(p) / MB for p in sorted(out.iterdir())}
    parts["all"] = size(out) / MB
    print(f"cosim benchmark --preset smoke --keep {keep}: {parts['all']:.1f} MB in all "
          f"({', '.join(f'{k} {v:.1f} MB' for k, v in parts.items() if k != 'all')}; {seconds:.0f} s)",
          flush=True)
    return parts


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--keep", choices=["best", "all"], default="best")
    p.add_argument("--preset", default="quick", help="preset of the run folders (default quick: 6 ACs)")
    p.add_argument("--steps", type=int, default=300, help="env steps of each run folder")
    p.add_argument("--skip-benchmark", action="store_true", help="only the run folders")
    p.add_argument("--skip-runs", action="store_true", help="only the smoke benchmark")
    p.add_argument("--out", type=Path, default=None, help="also write the figures as JSON")
    args = p.parse_args()
    figures = {"keep": args.keep}
    with tempfile.TemporaryDirectory(prefix="cosim-disk") as tmp:
        if not args.skip_runs:
            figures["runs"] = run_folders(Path(tmp), args.preset, args.steps, args.keep)
        if not args.skip_benchmark:
            figures["smoke_benchmark_mb"] = benchmark(Path(tmp), args.keep)
    if args.out:
        args.out.write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
