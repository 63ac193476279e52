"""A CleanRL-style PPO loop (``ppo_atari.py`` shape) on cosim's single-agent env.

Config, network, rollout, GAE, clipped loss: top to bottom in one file. It shows the
environment working unchanged inside the usual recipe: a Gymnasium vector env of
RecordEpisodeStatistics-wrapped single envs, uint8 images scaled in the network,
``reward_scale`` set on the environment. The defaults are a smoke run; train with
``cosim train`` for results.

    python examples/cleanrl_ppo.py --steps 256
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
from torch.distributions import Categorical

import cosim


@dataclass
class Args:
    steps: int = 256
    """total environment steps"""
    num_steps: int = 128
    """steps per rollout"""
    learning_rate: float = 2.5e-4
    """Adam learning rate"""
    gamma: float = 0.99
    """discount factor"""
    gae_lambda: float = 0.95
    """lambda of generalised advantage estimation"""
    num_minibatches: int = 4
    """minibatches per epoch"""
    update_epochs: int = 2
    """epochs over each rollout"""
    clip_coef: float = 0.1
    """PPO ratio clip"""
    ent_coef: float = 0.01
    """entropy bonus"""
    vf_coef: float = 0.5
    """value loss weight"""
    max_grad_norm: float = 0.5
    """gradient clip"""
    seed: int = 0
    """seed of torch, numpy and the environment"""


def make_env(seed: int):
    def thunk():
        env = cosim.single_env("env_1", background=False, pedestrians=False, horizon=128,
                               reward_scale=0.01)
        env = gym.wrappers.RecordEpisodeStatistics(env)
        env.action_space.seed(seed)
        return env

    return thunk


def layer_init(layer, std=2**0.5, bias_const=0.0):
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    def __init__(self, envs):
        super().__init__()
        h, w, c = envs.single_observation_space.shape
        self.network = nn.Sequential(
            layer_init(nn.Conv2d(c, 32, 8, stride=4)), nn.ReLU(),
            layer_init(nn.Conv2d(32, 64, 4, stride=2)), nn.ReLU(),
            layer_init(nn.Conv2d(64, 64, 3, stride=1)), nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():  # infer the flatten size with a dummy forward pass
            n_flat = self.network(torch.zeros(1, c, h, w)).shape[1]
        self.network.append(layer_init(nn.Linear(n_flat, 512)))
        self.network.append(nn.ReLU())
        self.actor = layer_init(nn.Linear(512, envs.single_action_space.n), std=0.01)
        self.critic = layer_init(nn.Linear(512, 1), std=1)

    def features(self, x):
        return self.network(x.permute(0, 3, 1, 2) / 255.0)  # uint8 HWC -> float CHW

    def get_value(self, x):
        return self.critic(self.features(x))

    def get_action_and_value(self, x, action=None):
        hidden = self.features(x)
        probs = Categorical(logits=self.actor(hidden))
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action), probs.entropy(), self.critic(hidden)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=Args.steps)
    parser.add_argument("--num-steps", type=int, default=Args.num_steps)
    args = Args(**{k: v for k, v in vars(parser.parse_args()).items()})
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    # libsumo runs one SUMO per process: one sync env here (more: see make_vec_async.py)
    envs = gym.vector.SyncVectorEnv([make_env(args.seed)])
    agent = Agent(envs)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)
    n_envs = envs.num_envs
    batch_size = args.num_steps * n_envs
    minibatch_size = batch_size // args.num_minibatches

    obs = torch.zeros((args.num_steps, n_envs) + envs.single_observation_space.shape, dtype=torch.uint8)
    actions = torch.zeros((args.num_steps, n_envs), dtype=torch.long)
    log_probs = torch.zeros((args.num_steps, n_envs))
    rewards = torch.zeros((args.num_steps, n_envs))
    dones = torch.zeros((args.num_steps, n_envs))
    values = torch.zeros((args.num_steps, n_envs))

    global_step, start = 0, time.time()
    next_obs, _ = envs.reset(seed=args.seed)
    next_obs, next_done = torch.as_tensor(next_obs), torch.zeros(n_envs)
    for iteration in range(1, max(1, args.steps // batch_size) + 1):
        for step in range(args.num_steps):
            global_step += n_envs
            obs[step], dones[step] = next_obs, next_done
            with torch.no_grad():
                action, log_prob, _, value = agent.get_action_and_value(next_obs.float())
            actions[step], log_probs[step], values[step] = action, log_prob, value.flatten()
            next_obs, reward, terminated, truncated, infos = envs.step(action.numpy())
            # an episode cut by the horizon is treated as ended (as CleanRL does)
            next_done = torch.as_tensor(np.logical_or(terminated, truncated), dtype=torch.float32)
            rewards[step] = torch.as_tensor(reward, dtype=torch.float32)
            next_obs = torch.as_tensor(next_obs)
            if "episode" in infos:
                for i in np.flatnonzero(infos["_episode"]):
                    print(f"global_step={global_step}, episodic_return={infos['episode']['r'][i]:.2f}")

        with torch.no_grad():  # GAE, bootstrapping from the value of the last observation
            next_value = agent.get_value(next_obs.float()).flatten()
            advantages = torch.zeros_like(rewards)
            last_gae = 0.0
            for t in reversed(range(args.num_steps)):
                next_non_terminal = 1.0 - (next_done if t == args.num_steps - 1 else dones[t + 1])
                next_values = next_value if t == args.num_steps - 1 else values[t + 1]
                delta = rewards[t] + args.gamma * next_values * next_non_terminal - values[t]
                last_gae = delta + args.gamma * args.gae_lambda * next_non_terminal * last_gae
                advantages[t] = last_gae
            returns = advantages + values

        b_obs = obs.reshape((-1,) + envs.single_observation_space.shape)
        b_actions, b_log_probs = actions.reshape(-1), log_probs.reshape(-1)
        b_advantages, b_returns = advantages.reshape(-1), returns.reshape(-1)
        b_inds = np.arange(batch_size)
        for _ in range(args.update_epochs):
            np.random.default_rng(args.seed + iteration).shuffle(b_inds)
            for lo in range(0, batch_size, minibatch_size):
                mb = b_inds[lo:lo + minibatch_size]
                _, new_log_prob, entropy, new_value = agent.get_action_and_value(
                    b_obs[mb].float(), b_actions[mb])
                ratio = (new_log_prob - b_log_probs[mb]).exp()
                mb_adv = b_advantages[mb]
                mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std() + 1e-8)
                pg_loss = torch.max(-mb_adv * ratio,
                                    -mb_adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
                v_loss = 0.5 * ((new_value.flatten() - b_returns[mb]) ** 2).mean()
                loss = pg_loss - args.ent_coef * entropy.mean() + args.vf_coef * v_loss
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()
        print(f"iteration {iteration}: losses/policy_loss={pg_loss.item():.4f} "
              f"losses/value_loss={v_loss.item():.4f} SPS={int(global_step / (time.time() - start))}")
    envs.close()
    print(f"done: {global_step} steps")


if __name__ == "__main__":
    main()
