"""The state track's speed (issue 61): env steps/s with 6 ACs, cameras off against on, and highway-env.

Three environments in one run, each ``--repeats`` runs of ``--steps`` steps (only ``step()``
is timed; a reset when every AC is done is not), random actions from fixed seeds:

- ``state``: ``cosim.parallel_env("env_2", obs="state")``, the Three-way in its traffic
  (background cars and pedestrians), 6 ACs, cameras off (no PyBullet mirror): the 65-number
  vector per AC (cosim/state.py);
- ``camera``: the same env with ``obs="image"``, each AC's 84x84 camera frame (TinyRenderer);
- ``highway``: highway-env's ``intersection-multi-agent-v2`` (if ``highway_env`` imports: the
  optional ``bench`` extra), 6 controlled vehicles, its Kinematics observation (15 vehicles x
  7 features per agent), integrated and observed at cosim's 10 Hz (``simulation_frequency``
  = ``policy_frequency`` = 10: one env step is 0.1 s of driving in all three) with IDM traffic
  seeded to cosim's vehicle count (``--highway-cars`` at the start, spawns at its default
  0.6 per second). Its default is 1 Hz decisions over 15 Hz integration (one step = 1 s).

Collisions do not end an episode in either (the test's conditions: 6 agents step
throughout): highway-env's episode ends when any controlled vehicle crashes, which with 6
of them (two pairs spawn in one lane) is at its first steps, so the run steps on after a
crash (a crashed vehicle stops) and resets at the time limit only, as cosim's test does.
Prints a Markdown table of medians, the mean number of vehicles on the road, and the ratios.

    python bench/state_track.py [--steps 300] [--repeats 3] [--highway-cars 6]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import cosim

AGENTS = 6
DT = 0.1  # seconds per step in all three (cosim's scenarios; highway-env set to match)


def run_cosim(obs: str, steps: int, seed: int) -> dict:
    env = cosim.parallel_env("env_2", num_agents=AGENTS, action_types="discrete", obs=obs,
                             terminate_on_collision=False, seed=seed)
    spaces = {a: env.action_space(a) for a in env.possible_agents}
    for i, s in enumerate(spaces.values()):
        s.seed(seed * 100 + i)
    _, infos = env.reset(seed=seed)
    elapsed, cars, done = 0.0, [], 0
    while done < steps:
        if not env.agents:
            env.reset(seed=seed + done)
        actions = {a: spaces[a].sample() for a in env.agents}
        t0 = time.perf_counter()
        _, _, _, _, infos = env.step(actions)
        elapsed += time.perf_counter() - t0
        info = next(iter(infos.values()))
        cars.append((info["n_vehicles"] + 1, info["n_pedestrians"]))
        done += 1
    mirror = env.unwrapped.mirror is not None
    env.close()
    return {"steps_per_s": steps / elapsed, "vehicles": float(np.mean([c[0] for c in cars])),
            "pedestrians": float(np.mean([c[1] for c in cars])), "mirror": mirror}


def highway_env(cars: int):
    import gymnasium
    import highway_env

    gymnasium.register_envs(highway_env)
    return gymnasium.make("intersection-multi-agent-v2", config={
        "controlled_vehicles": AGENTS, "initial_vehicle_count": cars,
        "simulation_frequency": round(1 / DT), "policy_frequency": round(1 / DT),
        "spawn_probability": 0.6 * DT,  # its default 0.6 per 1 s step, per second here too
        "duration": 60,  # s, as cosim's 600-step horizon
    })


def run_highway(steps: int, seed: int, cars: int) -> dict:
    env = highway_env(cars)
    env.action_space.seed(seed)
    env.reset(seed=seed)
    elapsed, count, done, crashed = 0.0, [], 0, 0
    while done < steps:
        action = env.action_space.sample()
        t0 = time.perf_counter()
        _, _, term, trunc, _ = env.step(action)  # term: a crash (stepped on, as in cosim's test)
        elapsed += time.perf_counter() - t0
        count.append(len(env.unwrapped.road.vehicles))
        crashed += int(np.any(term))
        done += 1
        if np.all(trunc):  # per agent in v2
            env.reset(seed=seed + done)
    env.close()
    return {"steps_per_s": steps / elapsed, "vehicles": float(np.mean(count)), "pedestrians": 0.0,
            "crashed": crashed / steps}


def median(runs: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in runs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--highway-cars", type=int, default=6,
                        help="highway-env's initial IDM vehicles (besides the 6 controlled)")
    args = parser.parse_args()
    results = {
        "state": [run_cosim("state", args.steps, 20 + r) for r in range(args.repeats)],
        "camera": [run_cosim("image", args.steps, 20 + r) for r in range(args.repeats)],
    }
    assert not any(r["mirror"] for r in results["state"]) and all(r["mirror"] for r in results["camera"])
    try:
        results["highway"] = [run_highway(args.steps, 20 + r, args.highway_cars) for r in range(args.repeats)]
        hw = ""
    except ImportError as exc:
        hw = f"highway-env not installed ({exc}; pip install -e '.[bench]'): skipped"
    labels = {"state": "cosim env_2, state track (cameras off)", "camera": "cosim env_2, 84x84 cameras",
              "highway": "highway-env intersection-multi-agent-v2, 10 Hz"}
    print(f"{AGENTS} agents, random actions, {args.repeats} x {args.steps} steps, medians\n")
    print("| env | steps/s | AC-steps/s | simulated s per s | vehicles on the road | pedestrians |")
    print("|---|---|---|---|---|---|")
    for key, runs in results.items():
        sps = median(runs, "steps_per_s")
        print(f"| {labels[key]} | {sps:.1f} | {AGENTS * sps:.0f} | {DT * sps:.1f} | "
              f"{median(runs, 'vehicles'):.1f} | {median(runs, 'pedestrians'):.1f} |")
    state, camera = median(results["state"], "steps_per_s"), median(results["camera"], "steps_per_s")
    print(f"\nstate / camera: {state / camera:.1f}x")
    if "highway" in results:
        high = median(results["highway"], "steps_per_s")
        print(f"state / highway-env: {state / high:.2f}x; camera / highway-env: {camera / high:.2f}x "
              f"(steps after a crash: {median(results['highway'], 'crashed'):.0%})")
    else:
        print(hw)


if __name__ == "__main__":
    main()
