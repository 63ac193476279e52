"""Twin Delayed DDPG (Fujimoto et al. 2018), and the machinery DDPG reuses.

TD3 = DDPG + three tricks: twin critics (the target takes their minimum),
target policy smoothing (clipped Gaussian noise on the target action) and
delayed actor/target updates. ``agents/ddpg.py`` is this class with the tricks
switched off (one critic, no target noise, policy delay 1), as in SB3.

Reads top to bottom: config, agent (act_batch / observe_batch / update), losses.
"""

from __future__ import annotations

import copy
import logging
from typing import ClassVar

import gymnasium
import numpy as np
import torch
import torch.nn.functional as F

from agents import observations
from agents.base import ReplayAgent, check_observation_space, due
from agents.buffers import ReplayBuffer
from agents.configs import AgentConfig, TD3Config
from agents.networks import (
    DeterministicActor,
    QEnsemble,
    encoder_features_dim,
    obs_to_tensor,
    polyak_update,
)

__all__ = ["TD3", "TD3Config"]

logger = logging.getLogger(__name__)

SATURATED = float(np.arctanh(0.99))
"""|pre-tanh| above which an action component counts as pinned at a bound (|tanh| > 0.99)."""


class TD3(ReplayAgent):
    """TD3 on a deterministic tanh actor and an ensemble of Q critics.

    The actor reads the critic's observation features, detached: for images
    that is the critic's Nature CNN, trained by the TD loss only (the SAC-AE /
    DrQ recipe, Yarats et al. 2021; an actor with its own CNN collapsed to
    bang-bang steering on our image task), for vectors it is the observation
    itself. One CNN forward then serves the actor and all critics.
    """

    optimizer_learning_rates: ClassVar[dict[str, str]] = {"actor_optimizer": "actor_learning_rate", "critic_optimizer": "critic_learning_rate"}

    algo = "td3"
    config_class: ClassVar[type[AgentConfig]] = TD3Config
    config: TD3Config

    @classmethod
    def check_spaces(cls, observation_space, action_space) -> None:
        if not isinstance(action_space, gymnasium.spaces.Box) or len(action_space.shape) != 1:
            raise ValueError(
                f"{cls.algo.upper()} needs a 1-D Box action space, got {action_space!r}; use PPO or DQN for Discrete"
            )
        check_observation_space(cls.algo, observation_space)

    def _build(self) -> None:
        cfg = self.config
        features = gymnasium.spaces.Box(-np.inf, np.inf, (encoder_features_dim(self.observation_space),), np.float32)
        self.actor = DeterministicActor(features, self.action_space, cfg.hidden).to(self.device)
        self.critic = QEnsemble(self.observation_space, self.action_space, cfg.n_critics, cfg.hidden).to(self.device)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_learning_rate)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_learning_rate)
        self.networks = {
            "actor": self.actor, "critic": self.critic,
            "actor_target": self.actor_target, "critic_target": self.critic_target,
        }
        self.optimizers = {"actor_optimizer": self.actor_optimizer, "critic_optimizer": self.critic_optimizer}
        self.buffer = ReplayBuffer(cfg.buffer_size, self.observation_space, self.action_space, seed=self.seed)
        self.low = self.action_space.low.astype(np.float32)
        self.high = self.action_space.high.astype(np.float32)
        self.half_range = (self.high - self.low) / 2.0
        self.random_low = self.low.copy()
        if cfg.random_low:
            floor = np.asarray(cfg.random_low, np.float32)
            if floor.shape != self.low.shape or np.any(floor < self.low) or np.any(floor >= self.high):
                raise ValueError(f"random_low {cfg.random_low} must give one value per action component "
                                 f"in [low, high) of {self.action_space}")
            self.random_low = floor
        self.random_until = max(cfg.random_steps, cfg.learning_starts)
        self.steps = 0
        self._updated_to = 0  # self.steps at the last update() call
        self.gradient_updates = 0

    def prepare_envs(self, num_envs: int) -> None:
        """One replay ring per environment (each ring's slots follow its own episodes)."""
        if self.buffer.columns == num_envs:
            return
        if len(self.buffer):
            raise RuntimeError(f"{self.algo} replay already holds {len(self.buffer)} transitions from "
                               f"{self.buffer.columns} env(s); cannot switch to {num_envs}")
        self.buffer = ReplayBuffer(self.config.buffer_size, self.observation_space, self.action_space,
                                   seed=self.seed, columns=num_envs)

    # ---- acting -----------------------------------------------------------------------
    @torch.no_grad()
    def act_batch(self, obs, columns: np.ndarray | None, deterministic: bool = False) -> np.ndarray:
        if not deterministic and self.steps < self.random_until:
            n = observations.rows(obs)
            return self.rng.uniform(self.random_low, self.high, (n, *self.low.shape)).astype(np.float32)
        return self.act_from(self.actor(self.critic.encode(obs_to_tensor(obs, self.device))), columns, deterministic)

    def acting_chain(self, deterministic: bool = False) -> tuple[torch.nn.Module, ...] | None:
        """The critic's encoder (QEnsemble.encode: the CNN, or a flatten of the floats) and the
        actor; none in the random phase, whose actions need no network."""
        if not deterministic and self.steps < self.random_until:
            return None
        return self.critic.encoder, self.actor

    @torch.no_grad()
    def act_from(self, outputs, columns: np.ndarray | None, deterministic: bool = False) -> np.ndarray:
        cfg, actions = self.config, outputs.cpu().numpy()
        if not deterministic:
            actions = actions + self.rng.normal(0.0, cfg.exploration_noise, actions.shape) * self.half_range
        return np.clip(actions, self.low, self.high).astype(np.float32)

    def observe_batch(self, obs, actions, rewards, next_obs, terminated, truncated, columns) -> None:
        scale = self.config.reward_scale
        for j, column in enumerate(np.asarray(columns).tolist()):
            action = np.asarray(actions[j], dtype=np.float32).reshape(self.action_space.shape)
            self.buffer.add(observations.take(obs, j), action, float(rewards[j]) * scale,
                            observations.take(next_obs, j), bool(terminated[j]), bool(truncated[j]), column=column)
        self.steps += len(columns)

    # ---- learning ---------------------------------------------------------------------
    def update(self) -> dict[str, float]:
        """The gradient steps due for the transitions observed since the last call."""
        cfg = self.config
        before, self._updated_to = self._updated_to, self.steps
        phases = due(before, self.steps, cfg.train_freq, start=cfg.learning_starts)
        metrics: dict[str, float] = {}
        for _ in range(cfg.gradient_steps * phases):
            metrics.update(self._gradient_step())
        return metrics

    def _gradient_step(self) -> dict[str, float]:
        cfg = self.config
        data = self.buffer.sample(cfg.batch_size, self.device)
        scale = self.actor.action_scale
        with torch.no_grad():
            # Target policy smoothing: clipped noise on the target action (0 for DDPG).
            noise = torch.randn(data.actions.shape, generator=self.generator, device=self.device)
            noise = (noise * cfg.target_policy_noise).clamp(-cfg.target_noise_clip, cfg.target_noise_clip)
            low, high = self.actor.action_bias - scale, self.actor.action_bias + scale
            next_features = self.critic_target.encode(data.next_obs)
            next_actions = (self.actor_target(next_features) + noise * scale).clamp(low, high)
            qf_next_target = torch.stack([
                self.critic_target.q_from_features(next_features, next_actions, i) for i in range(cfg.n_critics)
            ]).min(dim=0).values
            next_q_value = data.rewards + cfg.gamma * (1.0 - data.terminateds) * qf_next_target

        qf_values = self.critic(data.obs, data.actions)
        # Sum of the critics' MSEs (CleanRL's qf1_loss + qf2_loss).
        qf_loss = F.mse_loss(qf_values, next_q_value.expand_as(qf_values), reduction="none").mean(1).sum()
        self.critic_optimizer.zero_grad()
        qf_loss.backward()
        self.critic_optimizer.step()
        self.gradient_updates += 1
        metrics = {"losses/qf_loss": qf_loss.item(), "losses/qf_values": qf_values.mean().item()}

        if self.gradient_updates % cfg.policy_delay == 0:
            # Detached features: the actor's loss does not train the critic's encoder.
            with torch.no_grad():
                features = self.critic.encode(data.obs)
            pre = self.actor.preactivation(features)
            q = self.critic.q_from_features(features, self.actor.squash(pre), head=0)
            actor_loss = -q.mean()
            if cfg.pre_tanh_penalty > 0:
                actor_loss = actor_loss + cfg.pre_tanh_penalty * pre.pow(2).mean()
            if cfg.demo_bc > 0 and data.demos is not None and bool(data.demos.any()):
                demo_actions = self.actor.squash(pre[data.demos])
                # Weighed against the critic's scale (TD3+BC's lambda = alpha / mean|Q|): the
                # returns here run to thousands, beside which a bare squared distance is nothing.
                q_scale = q.detach().abs().mean().clamp(min=1.0)
                bc = F.mse_loss(demo_actions, data.actions[data.demos])
                actor_loss = actor_loss + cfg.demo_bc * q_scale * bc
            self.actor_optimizer.zero_grad()
            actor_loss.backward()
            self.actor_optimizer.step()
            polyak_update(self.actor.parameters(), self.actor_target.parameters(), cfg.tau)
            polyak_update(self.critic.parameters(), self.critic_target.parameters(), cfg.tau)
            metrics["losses/actor_loss"] = actor_loss.item()
            metrics["losses/actor_saturated"] = (pre.detach().abs() > SATURATED).float().mean().item()
        return metrics
