"""Full environment steps with the cameras drawn by TinyRenderer (CPU) and by EGL (GPU).

env_3 (four-way, background cars, pedestrians), 6 ACs, 84x84 cameras, one process: reset
(seed 0), 5 steps of action 0, then ``--steps`` steps of action 1 for every AC, timed, once
per renderer in the same run. A renderer that cannot start is reported in one line and the
other still runs (on a machine without a GPU, ``egl`` fails: cosim's ``renderer="auto"``
then uses TinyRenderer). EGL draws every mesh while TinyRenderer paints the flat layers into
a ground raster (docs/mirror.md), so the two cameras differ slightly (the mean pixel is
printed beside each rate).

    python bench/renderer_speed.py [--steps 150] [--renderers tiny egl]
"""

from __future__ import annotations

import argparse
import logging
import time

import cosim


def rate(renderer: str, steps: int, agents: int = 6) -> str:
    env = cosim.parallel_env("env_3", num_agents=agents, renderer=renderer)
    try:
        env.reset(seed=0)
        for _ in range(5):
            env.step({a: 0 for a in env.agents})
        t0, n, obs = time.perf_counter(), 0, {}
        while n < steps and env.agents:
            obs, *_ = env.step({a: 1 for a in env.agents})
            n += 1
        dt = time.perf_counter() - t0
    finally:
        env.close()
    mean = next(iter(obs.values())).mean() if obs else float("nan")
    return (f"renderer={renderer}: {n / dt:.1f} env steps/s, {agents * n / dt:.0f} AC-frames/s, "
            f"obs mean {mean:.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--renderers", nargs="+", choices=["tiny", "egl", "auto"], default=["tiny", "egl"])
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    for r in args.renderers:
        try:
            print(rate(r, args.steps), flush=True)
        except Exception as exc:  # noqa: BLE001 - one renderer failing must not hide the other
            print(f"renderer={r}: FAILED {type(exc).__name__}: {exc}", flush=True)


if __name__ == "__main__":
    main()
