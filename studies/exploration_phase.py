"""How far the DDPG/TD3 random phase drives the car: uniform random vs a throttle floor.

The first ``random_steps`` transitions of each DDPG/TD3 agent are uniform random
actions (TD3Config.random_steps, with ``random_low`` raising the lower end of the
draw per action component). This measures, under training conditions (3 ACs,
collisions end an AC's episode, the standard preset's 600-step horizon, spawn jitter
on), what those actions do to the car: metres driven per episode, the share of AC
steps at or above 1 m/s, DISTANCE (metres gained towards the goal), episode length
and return. The camera does not act on the dynamics, so the environment renders 8x8
frames to keep this fast; actions are drawn exactly as
``TD3.act`` draws its random phase (numpy ``uniform(low, high)``).

    python studies/exploration_phase.py [--envs env_1 ... env_5] [--steps 1000] [--lows -1 -0.5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from cosim.env import EPISODE_INFO, CosimParallelEnv
from cosim.scenario import available_scenarios


def measure(env_name: str, throttle_low: float, steps: int, seed: int = 0, horizon: int = 600) -> dict:
    env = CosimParallelEnv(env_name, num_agents=3, action_types="continuous", seed=seed, image_size=8,
                           horizon=horizon, terminate_on_collision=True)
    rng = np.random.default_rng(seed)
    low, high = np.array([throttle_low, -1.0], np.float32), np.ones(2, np.float32)
    speeds, episodes = [], []
    dt = env.scenario.dt  # seconds per step
    try:
        env.reset(seed=seed)
        for t in range(steps):
            if not env.agents:
                env.reset(seed=seed + 1 + t)
            actions = {a: rng.uniform(low, high).astype(np.float32) for a in env.agents}
            _, _, _, _, infos = env.step(actions)
            for info in infos.values():
                speeds.append(info["speed"])
                if EPISODE_INFO in info:
                    episodes.append(info[EPISODE_INFO])
    finally:
        env.close()
    speeds = np.asarray(speeds)
    metres = [e["mean_speed_kmh"] / 3.6 * e["length"] * dt for e in episodes]
    return {
        "env": env_name, "throttle_low": throttle_low, "episodes": len(episodes),
        "moving": float((speeds >= 1.0).mean()), "speed": float(speeds.mean()),
        "metres": float(np.mean(metres)) if metres else float("nan"),
        "DISTANCE": float(np.mean([e["DISTANCE"] for e in episodes])) if episodes else float("nan"),
        "length": float(np.mean([e["length"] for e in episodes])) if episodes else float("nan"),
        "return": float(np.mean([e["return"] for e in episodes])) if episodes else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=available_scenarios())
    parser.add_argument("--steps", type=int, default=1000, help="env steps per (env, throttle floor)")
    parser.add_argument("--lows", type=float, nargs="+", default=[-1.0, -0.5, 0.0],
                        help="lower ends of the throttle/brake draw (-1: uniform over the box)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print("| env | throttle draw | episodes | AC steps >= 1 m/s | mean speed m/s | metres driven "
          "| DISTANCE m | length | return |")
    print("|---|---|---|---|---|---|---|---|---|")
    start = time.monotonic()
    for env_name in args.envs:
        for low in args.lows:
            r = measure(env_name, low, args.steps, args.seed)
            print(f"| {r['env']} | U({low:g}, 1) | {r['episodes']} | {r['moving']:.2f} | {r['speed']:.1f} | "
                  f"{r['metres']:.1f} | {r['DISTANCE']:.1f} | {r['length']:.0f} | {r['return']:.0f} |",
                  flush=True)
    print(f"({time.monotonic() - start:.0f} s)")


if __name__ == "__main__":
    main()
