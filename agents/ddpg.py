"""Deep Deterministic Policy Gradient (Lillicrap et al. 2016) as TD3 with its tricks off.

One critic, no target-policy smoothing noise, actor and targets updated after
every critic step: exactly what SB3 does, so DDPG and TD3 share one tested
implementation (``agents/td3.py``) and differ only in configuration.
"""

from __future__ import annotations

from typing import ClassVar

from agents.configs import AgentConfig, DDPGConfig
from agents.td3 import TD3

__all__ = ["DDPG", "DDPGConfig"]


class DDPG(TD3):
    """DDPG: :class:`~agents.td3.TD3` with one critic, no target noise and no delay."""

    algo = "ddpg"
    config_class: ClassVar[type[AgentConfig]] = DDPGConfig
    config: DDPGConfig
