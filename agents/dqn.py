"""Deep Q-learning (Mnih et al. 2015) with a dueling head (Wang et al. 2016).

As SPEC section 5 asks: dueling, one atom, no noisy nets, 1-step targets (``n_step`` > 1:
multi-step targets, an option), a hard-updated target network, epsilon-greedy exploration
annealed linearly, Huber loss and gradient clipping. Double DQN (van Hasselt et al. 2016) is
an option, off in the paper preset. Demonstrations (Agent.observe_demonstration) can add
DQfD's large-margin loss (``demo_margin``) and a pre-training phase (:meth:`~agents.base.ReplayAgent.pretrain`).
Reads top to bottom: config, schedule, agent.
"""

from __future__ import annotations

import copy
import logging
from typing import ClassVar

import gymnasium
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from agents import observations
from agents.base import ReplayAgent, check_observation_space, due
from agents.buffers import ReplayBuffer
from agents.configs import DQNConfig
from agents.networks import DuelingQNetwork

__all__ = ["DQN", "DQNConfig", "linear_schedule", "margin_loss"]

logger = logging.getLogger(__name__)


def linear_schedule(start: float, end: float, duration: int, step: int) -> float:
    """Linear interpolation from ``start`` to ``end`` over ``duration`` steps, then ``end``."""
    fraction = min(max(step, 0) / duration, 1.0)
    return start + fraction * (end - start)


def margin_loss(q_values: torch.Tensor, actions: torch.Tensor, margin: float) -> torch.Tensor:
    """DQfD's supervised loss (Hester et al. 2018, eq. 2) on demonstrated transitions:
    mean of ``max_a [Q(s, a) + margin * (a != a_E)] - Q(s, a_E)``, 0 once the demonstrated
    action ``a_E`` (``actions``, shape (N, 1)) leads every other by ``margin``."""
    margins = torch.full_like(q_values, margin).scatter_(1, actions, 0.0)
    return ((q_values + margins).max(-1).values - q_values.gather(1, actions).squeeze(1)).mean()


class DQN(ReplayAgent):
    """Dueling DQN with a replay buffer and a hard-updated target network.

    Huber threshold: with delta 1 (RLlib, SB3) and Q-values in the tens, almost
    every TD error is in the linear zone, where the loss fits the *median*
    target; rare terminal transitions then barely pull Q down and on CartPole
    the Q-values diverged (to ~1e3 within 30k steps in our runs). The default
    delta 10 keeps ordinary TD errors quadratic; the paper preset keeps 1.
    """

    optimizer_learning_rates: ClassVar[dict[str, str]] = {"optimizer": "learning_rate"}

    algo = "dqn"
    config_class = DQNConfig
    config: DQNConfig

    @classmethod
    def check_spaces(cls, observation_space, action_space) -> None:
        if not isinstance(action_space, gymnasium.spaces.Discrete):
            raise ValueError(f"DQN needs a Discrete action space, got {action_space!r}; use DDPG or TD3 for Box")
        check_observation_space(cls.algo, observation_space)

    def _build(self) -> None:
        cfg = self.config
        n_actions = int(self.action_space.n)
        self.q_network = DuelingQNetwork(self.observation_space, n_actions, cfg.hidden).to(self.device)
        self.target_network = copy.deepcopy(self.q_network).requires_grad_(False)
        self.optimizer = torch.optim.Adam(self.q_network.parameters(), lr=cfg.learning_rate)
        self.networks = {"q_network": self.q_network, "target_network": self.target_network}
        self.optimizers = {"optimizer": self.optimizer}
        self.buffer = ReplayBuffer(cfg.buffer_size, self.observation_space, self.action_space, seed=self.seed)
        self.steps = 0
        self._updated_to = 0  # self.steps at the last update() call
        self.gradient_updates = 0

    def prepare_envs(self, num_envs: int) -> None:
        """One replay ring per environment (each ring's slots follow its own episodes)."""
        if self.buffer.columns == num_envs:
            return
        if len(self.buffer):
            raise RuntimeError(f"DQN replay already holds {len(self.buffer)} transitions from "
                               f"{self.buffer.columns} env(s); cannot switch to {num_envs}")
        self.buffer = ReplayBuffer(self.config.buffer_size, self.observation_space, self.action_space,
                                   seed=self.seed, columns=num_envs)

    @property
    def epsilon(self) -> float:
        """Current exploration rate."""
        cfg = self.config
        return linear_schedule(cfg.exploration_initial_eps, cfg.exploration_final_eps, cfg.exploration_steps, self.steps)

    def acting_chain(self, deterministic: bool = False) -> tuple[nn.Module, ...]:
        return (self.q_network,)

    @torch.no_grad()
    def act_from(self, outputs, columns: np.ndarray | None, deterministic: bool = False) -> np.ndarray:
        actions = outputs.argmax(-1).cpu().numpy()
        if not deterministic:
            explore = self.rng.random(len(actions)) < self.epsilon
            actions = np.where(explore, self.rng.integers(self.action_space.n, size=len(actions)), actions)
        return actions

    def observe_batch(self, obs, actions, rewards, next_obs, terminated, truncated, columns) -> None:
        # A truncated step is stored as non-terminal, so its target bootstraps.
        scale = self.config.reward_scale
        for j, column in enumerate(np.asarray(columns).tolist()):
            self.buffer.add(observations.take(obs, j), int(actions[j]), float(rewards[j]) * scale,
                            observations.take(next_obs, j), bool(terminated[j]), bool(truncated[j]), column=column)
        self.steps += len(columns)

    def update(self) -> dict[str, float]:
        """Target copies and gradient steps due for the transitions observed since the last call."""
        cfg = self.config
        before, self._updated_to = self._updated_to, self.steps
        if due(before, self.steps, cfg.target_update_interval):
            self.target_network.load_state_dict(self.q_network.state_dict())
        phases = due(before, self.steps, cfg.train_freq, start=cfg.learning_starts)
        if not phases:
            return {}
        metrics: dict[str, float] = {}
        for _ in range(cfg.gradient_steps * phases):
            metrics = self._gradient_step()
        return {**metrics, "charts/epsilon": self.epsilon}

    def _gradient_step(self) -> dict[str, float]:
        cfg = self.config
        data = self.buffer.sample(cfg.batch_size, self.device, n_step=cfg.n_step, gamma=cfg.gamma)
        discount = cfg.gamma if data.discounts is None else data.discounts
        with torch.no_grad():
            next_q = self.target_network(data.next_obs)
            if cfg.double_q:
                next_actions = self.q_network(data.next_obs).argmax(-1, keepdim=True)
                next_value = next_q.gather(1, next_actions).squeeze(1)
            else:
                next_value = next_q.max(-1).values
            td_target = data.rewards + discount * (1.0 - data.terminateds) * next_value
        q_all = self.q_network(data.obs)
        actions = data.actions.long().unsqueeze(1)
        q_values = q_all.gather(1, actions).squeeze(1)
        # Huber: quadratic near 0, linear (bounded gradients) for large TD errors.
        loss = F.huber_loss(q_values, td_target, delta=cfg.huber_delta)
        if cfg.demo_margin > 0 and data.demos is not None and bool(data.demos.any()):
            loss = loss + margin_loss(q_all[data.demos], actions[data.demos], cfg.demo_margin)
        self.optimizer.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(self.q_network.parameters(), cfg.max_grad_norm)
        self.optimizer.step()
        self.gradient_updates += 1
        return {"losses/td_loss": loss.item(), "losses/q_values": q_values.mean().item()}

    def _after_pretrain(self) -> None:
        """The target stays the initial network until the pre-training's end: copy it now."""
        self.target_network.load_state_dict(self.q_network.state_dict())
