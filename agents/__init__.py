"""Deep RL agents for cosim: six PyTorch algorithms behind one small interface.

This package sees only Gymnasium spaces and numpy arrays; it never imports the
simulator. ``agents/base.py`` defines the interface, ``agents/loop.py`` the
environment loop that documents the contract, ``agents/checkpoint.py`` the
self-describing checkpoint format, ``agents/registry.py`` the name -> class
table that :func:`load` uses, ``agents/configs.py`` the six algorithms' hyperparameter
dataclasses and ``agents/errors.py`` the root of every error this package raises on
purpose (these three are imported without torch, hence the lazy imports below).
"""

import importlib

# Submodules are imported on first use (PEP 562), so ``import agents.errors`` (which
# the command line imports to catch AgentError) does not import torch.
_EXPORTS = {
    "Agent": "agents.base", "AgentConfig": "agents.configs",
    "CheckpointError": "agents.checkpoint", "load_checkpoint": "agents.checkpoint",
    "clone": "agents.imitation",
    "save_checkpoint": "agents.checkpoint",
    "AgentError": "agents.errors",
    "DDPG": "agents.ddpg", "DDPGConfig": "agents.configs",
    "DQN": "agents.dqn", "DQNConfig": "agents.configs",
    "LoopStats": "agents.loop", "Progress": "agents.loop", "evaluate": "agents.loop",
    "run_loop": "agents.loop",
    "VectorEnv": "agents.vector", "InProcessVectorEnv": "agents.vector", "make_vector_env": "agents.vector",
    "polyak_update": "agents.networks",
    "PPO": "agents.ppo", "PPOConfig": "agents.configs",
    "A3CConfig": "agents.configs", "IMPALAConfig": "agents.configs",
    "ALGORITHMS": "agents.registry", "available": "agents.registry",
    "get_agent_class": "agents.registry",
    "gae": "agents.returns", "nstep_returns": "agents.returns", "vtrace": "agents.returns",
    "TD3": "agents.td3", "TD3Config": "agents.configs",
}


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'agents' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


__all__ = [
    "ALGORITHMS",
    "A3CConfig",
    "DDPG",
    "DQN",
    "PPO",
    "TD3",
    "Agent",
    "AgentConfig",
    "CheckpointError",
    "clone",
    "AgentError",
    "DDPGConfig",
    "DQNConfig",
    "IMPALAConfig",
    "InProcessVectorEnv",
    "LoopStats",
    "PPOConfig",
    "Progress",
    "TD3Config",
    "VectorEnv",
    "available",
    "evaluate",
    "gae",
    "get_agent_class",
    "load",
    "make_vector_env",
    "nstep_returns",
    "polyak_update",
    "run_loop",
    "save_checkpoint",
    "vtrace",
]


def load(path, device: str = "cpu", require_full: bool = False):
    """Rebuild any registered agent from a checkpoint file.

    Args:
        path: A file written by ``agent.save(path)``.
        device: Torch device for the rebuilt networks.
        require_full: Refuse a policy-only checkpoint (to resume training from it).

    Raises:
        CheckpointError: If the file is missing, corrupt, of another format, or
            holds an algorithm that is not registered, or is policy-only and
            ``require_full`` is set.
    """
    from agents.checkpoint import load_checkpoint

    return load_checkpoint(path, device=device, require_full=require_full)
