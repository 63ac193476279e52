"""RLlib (new API stack) support: an env-to-module connector casting uint8 images to float.

RLlib's default CNN encoders expect float observations; cosim's are uint8 images,
and in a multi-agent env the pipeline's observation space is a Dict of them.
:class:`UInt8ToFloat` maps every uint8 Box (inside Dicts too) to a float32 Box in
[0, 1] and scales each agent's observation. Needs the optional extra:
``pip install -e '.[ray]'``; see examples/rllib_ppo.py.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from ray.rllib.connectors.env_to_module.observation_preprocessor import (
    SingleAgentObservationPreprocessor,
)


def float_space(space: gym.Space) -> gym.Space:
    """``space`` with every uint8 Box replaced by a float32 Box in [0, 1] (Dicts recursed)."""
    if isinstance(space, gym.spaces.Dict):
        return gym.spaces.Dict({k: float_space(v) for k, v in space.spaces.items()})
    if isinstance(space, gym.spaces.Box) and space.dtype == np.uint8:
        return gym.spaces.Box(0.0, 1.0, space.shape, np.float32)
    return space


class UInt8ToFloat(SingleAgentObservationPreprocessor):
    """Env-to-module connector: uint8 images -> float32 in [0, 1], per agent."""

    def recompute_output_observation_space(self, input_observation_space, input_action_space):
        return float_space(input_observation_space)

    def preprocess(self, observation, episode):
        if isinstance(observation, np.ndarray) and observation.dtype == np.uint8:
            return observation.astype(np.float32) / 255.0
        return observation
