"""What acting and learning cost per step, piece by piece, for the end-to-end track (issue 59).

One torch thread, the learners' inputs (uint8 84x84x12 four-frame stacks, or the frozen
encoder's 4 x 512 float32 features with ``--features``), each number the median over
``--repeats`` interleaved rounds (every variant once per round, so a load that comes and goes
falls on all of them):

* **acting, 6 ACs, one env**: one forward pass per AC (``act_batch``, the path before issue 59)
  against one grouped pass for all six (agents/batched.py, ``act_all``), for PPO (A3C and IMPALA
  act with the same ActorCritic), DQN and TD3 (the critic's encoder and the actor; DDPG's are
  the same);
* **re-stacking one AC's weights** after it learnt (what the grouped pass pays per AC update);
* **one gradient step**: PPO's minibatch of 64, DQN's of 32 (double Q), TD3's of 64 (critic and,
  every second step, actor): with the image conversion before issue 59 (``obs.float()``, then a
  second float copy divided by 255) and with today's (agents/networks.py ``scaled_image``: one
  copy, scaled in place; bit for bit the same), and with Adam's ``foreach`` (the same numbers)
  and ``fused`` implementations (not bit for bit: 1 ulp apart, the lead's call).

    python bench/learner_costs.py [--repeats 15] [--features] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import gymnasium
import numpy as np
import torch

from agents import batched, networks
from agents.dqn import DQN, DQNConfig
from agents.ppo import PPO, PPOConfig
from agents.td3 import TD3, TD3Config

IMAGE = gymnasium.spaces.Box(0, 255, (84, 84, 12), np.uint8)
FEATURES = gymnasium.spaces.Box(-np.inf, np.inf, (2048,), np.float32)
DISCRETE = gymnasium.spaces.Discrete(9)
BOX = gymnasium.spaces.Box(np.array([-1, -1], np.float32), np.array([1, 1], np.float32))
ACS = 6


def old_scaled_image(obs: torch.Tensor) -> torch.Tensor:
    """NatureCNN's conversion before issue 59: two float copies."""
    return obs.float().permute(0, 3, 1, 2) / 255.0


def _configs(space) -> dict:
    vector = space is FEATURES
    hidden = {"hidden": (256, 256)} if vector else {}  # the presets' state_hidden for features
    return {
        "ppo": PPOConfig(rollout_steps=512, batch_size=64, epochs=4, ent_coef=0.01, **hidden),
        "dqn": DQNConfig(learning_starts=100, buffer_size=5000, batch_size=32, gradient_steps=1,
                         exploration_initial_eps=0.0, exploration_final_eps=0.0, **hidden),
        "td3": TD3Config(learning_starts=100, buffer_size=5000, batch_size=64, exploration_noise=0.1, **hidden),
    }


def _obs(space, rows: int, rng) -> np.ndarray:
    if space.dtype == np.uint8:
        return rng.integers(0, 256, (rows, *space.shape), dtype=np.uint8)
    return rng.normal(size=(rows, *space.shape)).astype(np.float32)


def acting_rows(space, rng) -> dict[str, callable]:
    """name -> a function that acts once for 6 ACs (and its twin on the other path)."""
    rows = {}
    for algo, cls in (("ppo", PPO), ("dqn", DQN), ("td3", TD3)):
        config = _configs(space)[algo]
        actions = BOX if algo == "td3" else DISCRETE
        group = {f"ac_{k}": cls.from_spaces(space, actions, config, seed=k) for k in range(ACS)}
        for agent in group.values():
            agent.steps = 10**6  # past DQN's epsilon and TD3's random phase: the network acts
        obs = [(a, np.zeros(1, np.int64), _obs(space, 1, rng)) for a in group]
        grouper = batched.Grouper()

        def each(group=group, obs=obs):
            for a, _envs, o in obs:
                group[a].act_batch(o, None)

        def grouped(group=group, obs=obs, grouper=grouper):
            batched.act_all(group, [(a, None, o) for a, _, o in obs], False, grouper)

        def restack(group=group, grouper=grouper):
            """ac_0 changed in place (as an optimiser step does); timed: the re-copy the next
            grouped pass makes (the stamps of all six ACs compared, ac_0's tensors copied)."""
            with torch.no_grad():
                for module in group["ac_0"].acting_chain():
                    for p in module.parameters():
                        p.mul_(1.0)
            t0 = time.perf_counter()
            copied = sum(net.refresh() for found in grouper.groups.values() for net in found)
            assert copied, "nothing was re-copied"
            return 1e3 * (time.perf_counter() - t0)

        grouped()  # build and check the grouped networks
        rows[f"act {algo}, one pass per AC"] = each
        rows[f"act {algo}, one grouped pass"] = grouped
        rows[f"re-stack one {algo} AC"] = restack
    return rows


def learner_rows(space, rng) -> dict[str, callable]:
    rows = {}
    for algo, cls in (("ppo", PPO), ("dqn", DQN), ("td3", TD3)):
        for adam in ("default", "foreach", "fused"):
            config = _configs(space)[algo]
            agent = cls.from_spaces(space, BOX if algo == "td3" else DISCRETE, config, seed=0)
            if adam != "default":
                for name, opt in agent.optimizers.items():
                    group = opt.param_groups[0]
                    new = torch.optim.Adam(opt.param_groups[0]["params"], lr=group["lr"], eps=group["eps"],
                                           **{adam: True})
                    agent.optimizers[name] = new
                    setattr(agent, name, new)
            step = _learner_step(algo, agent, space, rng)
            if space is IMAGE and adam == "default":
                rows[f"{algo} gradient step, conversion before issue 59"] = _with_old_conversion(step)
            rows[f"{algo} gradient step, Adam {adam}"] = step
    return rows


def _with_old_conversion(step):
    def run():
        networks_scaled = networks.scaled_image
        networks.scaled_image = old_scaled_image
        try:
            step()
        finally:
            networks.scaled_image = networks_scaled
    return run


def _learner_step(algo, agent, space, rng):
    if algo == "ppo":
        obs = torch.as_tensor(_obs(space, 64, rng))
        actions = torch.as_tensor(rng.integers(0, 9, 64))
        log_probs, logits = torch.full((64,), -2.2), torch.zeros(64, 9)
        advantages, returns = torch.randn(64), torch.randn(64)
        return lambda: agent._minibatch_step(obs, actions, log_probs, logits, advantages, returns)
    # a replay of consistent frame stacks (what the buffer needs): a stream of random frames
    k = 4 if space is IMAGE else 1
    frames = [_obs(gymnasium.spaces.Box(0, 255, (84, 84, 3), np.uint8), 1, rng)[0] if k > 1 else None
              for _ in range(400 + k)]
    for t in range(400):
        if k > 1:
            obs, nxt = (np.concatenate(frames[s:s + k], -1)[None] for s in (t, t + 1))
        else:
            obs, nxt = _obs(space, 1, rng), _obs(space, 1, rng)
        action = rng.uniform(-1, 1, (1, 2)).astype(np.float32) if algo == "td3" else rng.integers(0, 9, 1)
        agent.observe_batch(obs, action, np.array([rng.normal()], np.float32), nxt, np.array([False]),
                            np.array([False]), np.array([0]))
    return agent._gradient_step


def measure(rows: dict, repeats: int) -> dict[str, float]:
    times: dict[str, list[float]] = {name: [] for name in rows}
    for fn in rows.values():  # warm-up
        fn()
    for _ in range(repeats):
        for name, fn in rows.items():
            t0 = time.perf_counter()
            timed = fn()  # a row that times its own part returns it (ms)
            times[name].append(timed if isinstance(timed, float) else 1e3 * (time.perf_counter() - t0))
    return {name: statistics.median(ts) for name, ts in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--features", action="store_true", help="the frozen encoder's features (2048 floats)")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    space = FEATURES if args.features else IMAGE
    rng = np.random.default_rng(0)
    rows = {**acting_rows(space, rng), **learner_rows(space, rng)}
    result = measure(rows, args.repeats)
    what = "encoder features (2048 float32)" if args.features else "84x84x12 uint8 frame stacks"
    print(f"\ntorch {torch.__version__}, 1 thread, {what}, median of {args.repeats} interleaved rounds\n")
    print("| what | ms |\n|---|---|")
    for name, ms in result.items():
        print(f"| {name} | {ms:.2f} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
