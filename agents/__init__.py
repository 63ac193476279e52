"""Deep RL agents for cosim: six PyTorch algorithms behind one small interface.

This package sees only Gymnasium spaces and numpy arrays; it never imports the
simulator. ``agents/base.py`` defines the interface, ``agents/loop.py`` the
environment loop that documents the contract, ``agents/checkpoint.py`` the
self-describing checkpoint format and ``agents/registry.py`` the name -> class
table that :func:`load` uses.
"""

from agents.base import Agent, AgentConfig
from agents.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from agents.ddpg import DDPG, DDPGConfig
from agents.dqn import DQN, DQNConfig
from agents.loop import LoopStats, evaluate, run_loop
from agents.networks import polyak_update
from agents.ppo import PPO, PPOConfig
from agents.registry import ALGORITHMS, available, get_agent_class
from agents.returns import gae, nstep_returns, vtrace
from agents.td3 import TD3, TD3Config

__all__ = [
    "ALGORITHMS",
    "DDPG",
    "DQN",
    "PPO",
    "TD3",
    "Agent",
    "AgentConfig",
    "CheckpointError",
    "DDPGConfig",
    "DQNConfig",
    "LoopStats",
    "PPOConfig",
    "TD3Config",
    "available",
    "evaluate",
    "gae",
    "get_agent_class",
    "load",
    "nstep_returns",
    "polyak_update",
    "run_loop",
    "save_checkpoint",
    "vtrace",
]


def load(path, device: str = "cpu") -> Agent:
    """Rebuild any registered agent from a checkpoint file.

    Args:
        path: A file written by ``agent.save(path)``.
        device: Torch device for the rebuilt networks.

    Raises:
        CheckpointError: If the file is missing, corrupt, of another format, or
            holds an algorithm that is not registered.
    """
    return load_checkpoint(path, device=device)
