"""Training throughput on env_1 (--agents ACs, default 3): env steps/s and AC-frames/s, 1 vs N environments.

For each --envs value, in the same run on the same cores:

* the raw environment rate: the same vector runner (agents/vector.py) stepping
  N env_1 copies with uniform random actions, no learning, no networks;
* each algorithm training --steps environment steps with its quick-preset
  hyperparameters (learning_starts lowered to 200 so learning happens inside the
  window), through `eval.training.train.train` exactly as `cosim train --envs N` runs it.

Rates: "steady" counts env steps (summed over the N environments) over the time
inside the loop (reset, step, act, learn: the loop's own clocks; process and
simulator start-up excluded); "wall" is steps over the whole train() call,
start-up included. AC-frames are agent transitions (one camera frame each).
Every row uses the same torch thread count (--torch-threads, default 1): on a
busy 2-core machine two OpenMP threads made one CNN forward 20x slower.
A3C and IMPALA step the same vector env (`--envs N`: A3C one learner thread per
environment, IMPALA one learner acting in all of them); their steady rate is
the trainer's own clock from the first reset (agents/loop.py Progress.timing).

    python bench/train_throughput.py [--steps 1500] [--envs 1 2] [--algos ppo dqn td3 a3c impala]
    python bench/train_throughput.py --agents 6 --envs 1 --algos ppo a3c impala dqn ddpg td3   # the presets' ACs
    python bench/train_throughput.py --device cuda --envs 1 4 8 16 --algos ppo dqn td3   # on a GPU machine
    python bench/train_throughput.py --agents 6 --envs 1 --algos ppo dqn --share-params both   # sharing vs not
    python bench/train_throughput.py --agents 6 --envs 1 --algos ppo dqn --action-repeat 1 2   # action repeat
    python bench/train_throughput.py --agents 6 --envs 1 --algos dqn ddpg td3 --train-freq 8   # update-to-data ratio
    python bench/train_throughput.py --agents 6 --envs 1 --encoder enc.pt   # heads on a frozen encoder (issue 59)
    python bench/train_throughput.py --agents 6 --envs 1 --algos ppo a3c impala dqn ddpg td3 --steps 800 \
        --variants after today encoder --encoder enc.pt --repeats 3   # issue 59: before, after, encoder

``--train-freq 8`` adds, for DQN, DDPG and TD3, a row trained with one gradient step per 8 of
each AC's transitions (``--set train_freq=8``; the quick preset makes one per 4) and a table of
the ratio (train_freq 8 / the preset's row, steady env steps/s): the `standard` presets of DQN
and TD3 use 8 since 2026-11-26 (docs/benchmarks.md "Update-to-data ratio").

``--share-params on`` trains PPO/DQN/DDPG/TD3 with one network for all ACs (`cosim train
--share-params`; A3C and IMPALA rows stay independent); ``both`` trains each such algorithm
both ways in the same run and adds a table of the ratio (shared / independent, steady rate).

``--action-repeat 1 2`` trains every algorithm with each action held for 1 and for 2 env steps
(``cosim train --set action_repeat=2``, docs/task.md "Action repeat") in the same run and adds
a table of the ratio (repeat R / repeat 1, steady env steps/s). With R > 1 the loop's own clock
counts decisions: the steady env steps/s is R times its rate, the AC-frames/s its transitions.

``--variants after today encoder`` (issue 59) trains every algorithm three ways in the same run:
``after`` is the row as the code runs today (the plain row); ``today`` is the end-to-end path
before issue 59 (``--set batched_acting=false``, one forward pass per AC; PPO's
``shared_value_grad=1``; NatureCNN's two-copy image conversion, patched in this process);
``encoder`` learns heads on the frozen encoder of ``--encoder FILE``. DDPG's and TD3's random
phase is cut to 200 steps in these rows (the quick preset's 1,000 would fill the window, so their
networks would never act in it). ``--repeats R`` runs R rounds; in each, per algorithm, the raw
env right before the algorithm's rows (in the given order in odd rounds, reversed in even ones),
so every ratio (training / raw env, after / today) is taken within minutes on a machine whose
load moves; the tables give the medians over rounds.

``--device cuda`` puts the PPO/DQN/DDPG/TD3 learners on the GPU (A3C and IMPALA learn on
CPU whatever the device); without a CUDA device it stops at once with one line saying so.
The last table is the one the README's GPU rows take: env steps/s per algorithm and
--envs value, against the targets of issue 29 (PPO >= 1,000, DQN/TD3 >= 600 at 16 envs).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from eval.training.train import make_config, make_env, train

AGENTS = 3  # the default of --agents: the first tables of docs/benchmarks.md were taken with 3 ACs
TARGETS = {"ppo": 1000.0, "dqn": 600.0, "td3": 600.0}  # env steps/s at 16 envs on a GPU (issue 29)


def raw_env_rate(n: int, steps: int, seed: int = 3, agents: int = AGENTS) -> dict[str, float]:
    """Random actions through the vector runner: env steps/s and AC-frames/s, start-up excluded."""
    from agents.vector import make_vector_env

    cfg = make_config("ppo", "env_1", "quick", agents=agents, steps=steps, seed=seed, envs=n)
    venv = make_vector_env([functools.partial(make_env, cfg, seed + i) for i in range(n)])
    rng = np.random.default_rng(seed)
    try:
        t0 = time.perf_counter()
        state = venv.reset(seed=seed)
        done = frames = 0
        while done < steps:
            acts = {a: rng.integers(venv.action_space(a).n, size=n) for a in venv.possible_agents}
            state = venv.step(acts)
            done += n
            frames += int(sum(state.active[a].sum() for a in venv.possible_agents))
        dt = time.perf_counter() - t0
    finally:
        venv.close()
    return {"steps_s": done / dt, "frames_s": frames / dt}


TODAY = {"batched_acting": False}
"""``--variants today``: the agents' settings before issue 59 (with PPO's :data:`TODAY_PPO`)."""
TODAY_PPO = {"shared_value_grad": 1.0, "value_norm": "none"}


def old_scaled_image(obs):
    """NatureCNN's image conversion before issue 59 (two float copies; the same numbers)."""
    return obs.float().permute(0, 3, 1, 2) / 255.0


def train_rate(algo: str, n: int, steps: int, out: str, threads: int,
               agents: int = AGENTS, device: str = "cpu", share: bool = False, repeat: int = 1,
               train_freq: int | None = None, encoder: str | None = None, today: bool = False,
               random_steps: int | None = None) -> dict[str, float]:
    cfg = make_config(algo, "env_1", "quick", agents=agents, steps=steps, seed=3,
                      envs=n, device=device, torch_threads=threads, share_params=share, encoder=encoder,
                      validation_episodes=0)  # the learning loop alone: validation is timed apart
    changes = {"action_repeat": repeat} | ({"learning_starts": 200} if hasattr(cfg.agent_config, "learning_starts") else {})
    if random_steps is not None and hasattr(cfg.agent_config, "random_steps"):  # DDPG/TD3's random phase
        changes["random_steps"] = random_steps
    if train_freq is not None:
        changes["train_freq"] = train_freq
    if today:
        changes |= TODAY | (TODAY_PPO if algo == "ppo" else {})
    cfg = dataclasses.replace(cfg, agent_config=cfg.agent_config.replace(**changes))
    from agents import networks

    conversion = networks.scaled_image
    networks.scaled_image = old_scaled_image if today else conversion  # this process's learners
    t0 = time.monotonic()
    try:
        run = train(cfg, Path(out), quiet=True, progress=False)
    finally:
        networks.scaled_image = conversion
    wall = time.monotonic() - t0
    state = json.loads((run / "state.json").read_text())
    timing = state.get("timing", {})
    done = int(state["env_steps"])
    # the loop's clock counts its steps, each `repeat` env steps
    return {"wall_s": done / wall, "steps_s": repeat * timing.get("time/env_steps_per_s", float("nan")),
            "frames_s": timing.get("time/agent_steps_per_s", float("nan"))}


def check_device(device: str) -> None:
    """Stop with one line (exit 2) when ``--device cuda`` is asked for and torch sees no GPU."""
    import torch

    if device == "cuda" and not torch.cuda.is_available():
        sys.stderr.write(f"bench/train_throughput.py: --device cuda asked for, but torch {torch.__version__} "
                         f"sees no CUDA device (built with CUDA {torch.version.cuda}); run it on a GPU "
                         "machine or use --device cpu\n")
        raise SystemExit(2)


def device_name(device: str) -> str:
    import torch

    return torch.cuda.get_device_name(0) if device == "cuda" else "CPU"


def print_target_table(rows: dict, algos: list[str], envs: list[int], device: str) -> None:
    """Env steps/s (steady) per algorithm and --envs value, and the target (at 16 envs)."""
    print(f"\n| algorithm ({device}) | " + " | ".join(f"{n} env(s)" for n in envs) + " | target | met |")
    print("|---|" + "---|" * len(envs) + "---|---|")
    for algo in algos:
        rates = [rows[(algo, n)]["steps_s"] for n in envs]
        target = TARGETS.get(algo)
        met = "" if target is None or 16 not in envs else \
            ("yes" if rows[(algo, 16)]["steps_s"] >= target else "no")
        print(f"| {algo} | " + " | ".join(f"{r:.0f}" for r in rates)
              + f" | {'' if target is None else f'>= {target:,.0f} at 16 envs'} | {met} |")


def print_ratio_table(rows: dict, algos: list[str], envs: list[int], variants: list[str]) -> None:
    """Each variant's steady env steps/s over the plain row's, per algorithm and --envs value."""
    for variant in variants:
        print(f"\n| algorithm | envs | {variant} / plain (steady env steps/s) |\n|---|---|---|")
        for n in envs:
            for algo in algos:
                if (f"{algo} {variant}", n) in rows and (algo, n) in rows:
                    ratio = rows[(f"{algo} {variant}", n)]["steps_s"] / rows[(algo, n)]["steps_s"]
                    print(f"| {algo} | {n} | {ratio:.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--envs", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--agents", type=int, default=AGENTS, help="ACs per environment")
    parser.add_argument("--algos", nargs="+", default=["ppo", "dqn", "td3", "a3c", "impala"])
    parser.add_argument("--torch-threads", type=int, default=1,
                        help="the trainer's torch threads for every row (0: cosim train's default)")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                        help="torch device of the PPO/DQN/DDPG/TD3 learners (default cpu)")
    parser.add_argument("--share-params", choices=["off", "on", "both"], default="off",
                        help="one network for all ACs in ppo/dqn/ddpg/td3 (both: each way, and the ratio)")
    parser.add_argument("--action-repeat", type=int, nargs="+", default=[1],
                        help="train every row with each action held this many env steps (several: each, and the ratio)")
    parser.add_argument("--train-freq", type=int, nargs="+", default=[],
                        help="DQN/DDPG/TD3 also with one gradient step per this many of each AC's transitions "
                             "(rows 'algo train_freq F' beside the quick preset's, and the ratio)")
    parser.add_argument("--encoder", default=None, metavar="FILE",
                        help="every training row learns heads on this frozen perception encoder (cosim train "
                             "--encoder; the raw env rows stay the plain camera env); with --variants encoder, "
                             "only those rows")
    parser.add_argument("--variants", nargs="+", choices=["after", "today", "encoder"], default=None,
                        help="issue 59: each algorithm as the code runs (after), as before issue 59 (today), "
                             "and on --encoder (encoder), in the same run")
    parser.add_argument("--repeats", type=int, default=1,
                        help="every row this many times, round by round; the tables give the medians")
    args = parser.parse_args()
    check_device(args.device)
    if args.variants is not None:
        if "encoder" in args.variants and not args.encoder:
            parser.error("--variants encoder needs --encoder FILE")
        return run_variants(args)
    rate = functools.partial(train_rate, encoder=args.encoder)
    raw: dict[int, dict] = {}
    rows: dict[tuple[str, int], dict] = {}
    with tempfile.TemporaryDirectory() as out:
        for n in args.envs:
            raw[n] = raw_env_rate(n, args.steps, agents=args.agents)
            print(f"raw env, {n} env(s): {raw[n]}", flush=True)
            for algo in args.algos:
                can_share = algo not in ("a3c", "impala")
                for r in (x for x in args.action_repeat if x != 1):
                    rows[(f"{algo} repeat {r}", n)] = rate(algo, n, args.steps, out, args.torch_threads,
                                                           args.agents, args.device, repeat=r)
                    print(f"{algo} repeat {r}, {n} env(s): {rows[(f'{algo} repeat {r}', n)]}", flush=True)
                if 1 not in args.action_repeat:
                    continue
                if args.share_params != "on" or not can_share:
                    rows[(algo, n)] = rate(algo, n, args.steps, out, args.torch_threads,
                                           args.agents, args.device)
                    print(f"{algo}, {n} env(s): {rows[(algo, n)]}", flush=True)
                if args.share_params != "off" and can_share:
                    key = (algo, n) if args.share_params == "on" else (f"{algo} shared", n)
                    rows[key] = rate(algo, n, args.steps, out, args.torch_threads, args.agents,
                                     args.device, share=True)
                    print(f"{algo} shared, {n} env(s): {rows[key]}", flush=True)
                # the algorithms whose config has a train_freq (DQN, DDPG, TD3)
                has_freq = hasattr(make_config(algo, "env_1", "quick").agent_config, "train_freq")
                for f in args.train_freq if has_freq else ():
                    key = (f"{algo} train_freq {f}", n)
                    rows[key] = rate(algo, n, args.steps, out, args.torch_threads, args.agents,
                                     args.device, train_freq=f)
                    print(f"{key[0]}, {n} env(s): {rows[key]}", flush=True)
    shared = {"off": "", "on": ", one network for all ACs (--share-params)", "both": ""}[args.share_params]
    shared += f", heads on the frozen encoder {args.encoder}" if args.encoder else ""
    print(f"\n{args.steps} env steps per row, env_1, {args.agents} ACs, quick preset, learners on "
          f"{device_name(args.device)}, torch threads {args.torch_threads or 'default'}{shared}\n")
    names = [name for algo in args.algos
             for name in (algo, f"{algo} shared", *(f"{algo} repeat {r}" for r in args.action_repeat),
                          *(f"{algo} train_freq {f}" for f in args.train_freq))
             if any(key[0] == name for key in rows)]
    print("| what | envs | env steps/s (steady) | AC-frames/s (steady) | env steps/s (wall) "
          "| training / raw env (steady) |")
    print("|---|---|---|---|---|---|")
    for n in args.envs:
        r = raw[n]
        print(f"| raw env (random actions) | {n} | {r['steps_s']:.1f} | {r['frames_s']:.1f} | | 1.00 |")
        for algo in names:
            t = rows[(algo, n)]
            print(f"| {algo} | {n} | {t['steps_s']:.1f} | {t['frames_s']:.1f} | {t['wall_s']:.1f} "
                  f"| {t['steps_s'] / r['steps_s']:.2f} |")
    if 1 in args.action_repeat:
        print_target_table(rows, args.algos, args.envs, args.device)
    print_ratio_table(rows, args.algos, args.envs, [f"repeat {r}" for r in args.action_repeat if r != 1])
    if args.share_params == "both":
        print_ratio_table(rows, args.algos, args.envs, ["shared"])
    print_ratio_table(rows, args.algos, args.envs, [f"train_freq {f}" for f in args.train_freq])
    if len(args.envs) > 1 and "ppo" in args.algos:
        lo, hi = args.envs[0], args.envs[-1]
        print(f"\nPPO --envs {hi} / --envs {lo} (steady): {rows[('ppo', hi)]['steps_s'] / rows[('ppo', lo)]['steps_s']:.2f}x")


def run_variants(args) -> None:
    """``--variants``: per --envs value, ``--repeats`` rounds; in each round, per algorithm, the
    raw env and then the algorithm's variant rows, one after another, so each ratio compares rows
    taken minutes apart (on a shared machine the load moves between rounds). The tables give
    each row's median rate, and the median over the rounds of each round's ratios (training /
    the raw env measured just before it; after / today)."""
    import os

    names = {"after": "", "today": " today", "encoder": " encoder"}
    raw_name = "raw env (random actions)"
    runs: dict[tuple[str, int], list[dict]] = {}
    ratios: dict[tuple[str, int], list[float]] = {}
    speedups: dict[tuple[str, int], list[float]] = {}
    with tempfile.TemporaryDirectory() as out:
        for n in args.envs:
            for r in range(args.repeats):
                for algo in args.algos:
                    raw = raw_env_rate(n, args.steps, agents=args.agents)
                    runs.setdefault((raw_name, n), []).append(raw)
                    print(f"round {r + 1}: raw env before {algo}, {n} env(s): {raw}", flush=True)
                    got = {}
                    for variant in (args.variants if r % 2 == 0 else args.variants[::-1]):  # no order bias
                        key = (algo + names[variant], n)
                        got[variant] = train_rate(
                            algo, n, args.steps, out, args.torch_threads, args.agents, args.device,
                            encoder=args.encoder if variant == "encoder" else None, today=variant == "today",
                            random_steps=200)
                        runs.setdefault(key, []).append(got[variant])
                        ratios.setdefault(key, []).append(got[variant]["steps_s"] / raw["steps_s"])
                        print(f"round {r + 1}: {key[0]}, {n} env(s): {got[variant]}", flush=True)
                    if "after" in got and "today" in got:
                        speedups.setdefault((algo, n), []).append(got["after"]["steps_s"] / got["today"]["steps_s"])
    medians = {key: {m: statistics.median(x[m] for x in xs) for m in xs[0]} for key, xs in runs.items()}
    print(f"\n{args.steps} env steps per row, env_1, {args.agents} ACs, quick preset (learning_starts 200, "
          f"DDPG/TD3 random phase 200), learners on {device_name(args.device)}, torch threads "
          f"{args.torch_threads or 'default'}, {args.repeats} round(s); load average "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())} at the end\n")
    print("| what | envs | env steps/s (steady, median) | AC-frames/s (steady) | env steps/s (wall) "
          "| training / raw env (median of the rounds) | rounds (steady env steps/s) |")
    print("|---|---|---|---|---|---|---|")
    for n in args.envs:
        for key, m in medians.items():
            if key[1] != n:
                continue
            raw_row = key[0] == raw_name
            wall = "" if raw_row else f"{m['wall_s']:.1f}"
            ratio = "1.00" if raw_row else f"{statistics.median(ratios[key]):.2f}"
            each = ", ".join(f"{x['steps_s']:.1f}" for x in runs[key])
            print(f"| {key[0]} | {n} | {m['steps_s']:.1f} | {m['frames_s']:.1f} | {wall} | {ratio} | {each} |")
    if speedups:
        print("\n| algorithm | envs | after / today (median of the rounds) | each round |\n|---|---|---|---|")
        for key, values in speedups.items():
            print(f"| {key[0]} | {key[1]} | {statistics.median(values):.2f} | {', '.join(f'{v:.2f}' for v in values)} |")


if __name__ == "__main__":
    main()
