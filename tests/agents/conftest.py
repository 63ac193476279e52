"""Shared fixtures for the agents tests: small spaces and fast configs."""

import functools

import gymnasium as gym
import numpy as np
import pytest
import torch

from agents.ddpg import DDPGConfig
from agents.dqn import DQNConfig
from agents.ppo import PPOConfig
from agents.td3 import TD3Config

VECTOR_OBS = gym.spaces.Box(-np.inf, np.inf, (4,), np.float32)
DISCRETE = gym.spaces.Discrete(2)
PENDULUM_OBS = gym.spaces.Box(-8.0, 8.0, (3,), np.float32)
BOX = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)

# Configs that learn within a few hundred steps, so every code path runs in a smoke test.
FAST = {
    "ppo": PPOConfig(rollout_steps=64, batch_size=16, epochs=2),
    "dqn": DQNConfig(learning_starts=32, batch_size=16, train_freq=1, target_update_interval=50, hidden=(64, 64),
                     exploration_steps=100, buffer_size=1000),
    "ddpg": DDPGConfig(learning_starts=32, batch_size=16, buffer_size=1000),
    "td3": TD3Config(learning_starts=32, batch_size=16, buffer_size=1000),
}
SPACES = {
    "ppo": (VECTOR_OBS, DISCRETE),
    "dqn": (VECTOR_OBS, DISCRETE),
    "ddpg": (PENDULUM_OBS, BOX),
    "td3": (PENDULUM_OBS, BOX),
}
CARTPOLE = functools.partial(gym.make, "CartPole-v1")
CARTPOLE_SPACES = (gym.spaces.Box(-np.inf, np.inf, (4,), np.float32), gym.spaces.Discrete(2))


class Explodes(gym.Wrapper):
    """CartPole that raises after some steps: a simulator crash inside a worker or actor."""

    def __init__(self, after: int):
        super().__init__(gym.make("CartPole-v1"))
        self.after, self.steps = after, 0

    def step(self, action):
        self.steps += 1
        if self.steps > self.after:
            raise RuntimeError("simulated simulator crash")
        return super().step(action)


def model_weights(agent) -> torch.Tensor:
    """All of an A3C/IMPALA agent's model parameters as one flat copy."""
    return torch.cat([p.detach().flatten().clone() for p in agent.model.parameters()])


GYM_ENV = {"ppo": "CartPole-v1", "dqn": "CartPole-v1", "ddpg": "Pendulum-v1", "td3": "Pendulum-v1"}


@pytest.fixture(autouse=True)
def _one_thread():
    """Tests share 2 cores with other work: keep torch single-threaded."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
