"""What Discrete(9) can still drive when an action is held for R steps (docs/task.md,
"Action repeat"): the discrete autopilot (the ceiling of a discrete learner, whose steering
pulses between table entries) with each of its choices held R environment steps, 6 ACs,
background traffic, the held-out seeds 10,000, 10,001, ..., no camera (eval/testing/validity.py
``run_policy``). Deterministic: the same table on any machine.

    python bench/action_repeat_ceiling.py [--envs env_3 env_4] [--repeats 1 2 3 4] [--episodes 3]
"""

from __future__ import annotations

import argparse
import time

from cosim.scenario import load_scenario
from eval.testing.validity import run_policy


def row(env: str, repeat: int, episodes: int) -> str:
    t0 = time.perf_counter()
    df = run_policy(load_scenario(env), "autopilot-discrete", 6, episodes, hold=repeat)
    slots = df.groupby("agent")["goal"].mean()
    per_slot = " ".join(f"{a}:{v:.2f}" for a, v in slots.items())
    return (f"| {env} | {repeat} | {df['goal'].mean():.2f} | {df['collision_steps'].mean():.2f} | "
            f"{df['return'].mean():.1f} | {per_slot} | {time.perf_counter() - t0:.0f} s |")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", nargs="+", default=["env_3", "env_4"])
    p.add_argument("--repeats", nargs="+", type=int, default=[1, 2, 3, 4])
    p.add_argument("--episodes", type=int, default=3)
    args = p.parse_args(argv)
    print(f"autopilot-discrete, 6 ACs, {args.episodes} held-out episodes per row")
    print("| env | R | goal rate | contact steps / AC-episode | return / AC-episode | goal rate per slot | time |")
    print("|---|---|---|---|---|---|---|")
    for env in args.envs:
        for repeat in args.repeats:
            print(row(env, repeat, args.episodes), flush=True)


if __name__ == "__main__":
    main()
