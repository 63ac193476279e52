"""Proximal Policy Optimisation (Schulman et al. 2017) for Discrete action spaces.

Reads top to bottom: config, agent (act_batch / observe_batch / update), loss. The loss is
the clipped surrogate PLUS an adaptive KL penalty, as in RLlib (which the
paper used): ``coef *= 1.5`` when the KL exceeds twice its target, ``*= 0.5``
when it falls below half of it. Advantages come from GAE over one rollout of
``rollout_steps`` transitions of this agent, and truncated episodes bootstrap
from the value of their final observation. With N environments the rollout
holds the agent's ``rollout_steps`` transitions from all of them (about
``rollout_steps / N`` per environment, so the learning per transition does not
change with N), and GAE runs over each environment's column separately.

Two options on the value loss (issue 59, docs/agents.md), both off in the library's presets:
``shared_value_grad`` scales the value loss's gradient into an encoder the value shares with the
policy (images), so that it does not swamp the policy's; ``value_norm`` learns the value on returns normalised by their running mean
and standard deviation (:class:`RunningMeanStd`), values denormalised wherever they are used.
"""

from __future__ import annotations

import collections
import logging
from typing import Any, ClassVar

import gymnasium
import numpy as np
import torch
from torch import nn
from torch.distributions import Categorical, kl_divergence

from agents import observations
from agents.base import Agent, check_observation_space
from agents.buffers import RolloutBuffer
from agents.configs import PPOConfig
from agents.networks import ActorCritic, obs_to_tensor
from agents.returns import gae

__all__ = ["PPO", "PPOConfig", "RunningMeanStd"]

logger = logging.getLogger(__name__)


class PPO(Agent):
    """Clipped-surrogate PPO with an adaptive KL penalty on one ActorCritic network."""

    optimizer_learning_rates: ClassVar[dict[str, str]] = {"optimizer": "learning_rate"}

    algo = "ppo"
    config_class = PPOConfig
    config: PPOConfig

    @classmethod
    def check_spaces(cls, observation_space, action_space) -> None:
        if not isinstance(action_space, gymnasium.spaces.Discrete):
            raise ValueError(f"PPO here supports Discrete action spaces, got {action_space!r}; use DDPG or TD3 for Box")
        check_observation_space(cls.algo, observation_space)

    def _build(self) -> None:
        cfg = self.config
        n_actions = int(self.action_space.n)
        self.net = ActorCritic(self.observation_space, n_actions, cfg.hidden).to(self.device)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=cfg.learning_rate, eps=1e-5)
        self.networks = {"net": self.net}
        self.optimizers = {"optimizer": self.optimizer}
        self.buffer = RolloutBuffer(cfg.rollout_steps, self.observation_space, n_logits=n_actions)
        self.kl_coef = cfg.kl_coef
        self.iterations = 0
        self.steps = 0
        shared = self.net.value_encoder is None
        self.value_norm = cfg.value_norm == "all" or (cfg.value_norm == "shared" and shared)
        self.value_stats = RunningMeanStd()  # of the returns, when value_norm: the value head's scale
        # act_batch's (action, log prob, value, logits) per env, oldest first: the vector loop acts
        # at t + 1 before it observes t, so up to two are pending (bounded for evaluation-only use)
        self._column_cache: dict[int, collections.deque] = {}
        self._column_next: dict[int, np.ndarray] = {}  # env -> next_obs of its last transition, if it went on

    # ---- acting -----------------------------------------------------------------------
    def prepare_envs(self, num_envs: int) -> None:
        self._column_cache.clear()  # nothing acted before (e.g. an evaluation) is waiting for observe

    def acting_chain(self, deterministic: bool = False) -> tuple[nn.Module, ...]:
        return (self.net,)

    @torch.no_grad()
    def act_from(self, outputs, columns: np.ndarray | None, deterministic: bool = False) -> np.ndarray:
        logits, values = outputs
        if deterministic:
            actions = logits.argmax(-1)
        else:
            actions = torch.multinomial(torch.softmax(logits, -1), 1, generator=self.generator)[:, 0]
        log_probs = torch.log_softmax(logits, -1).gather(1, actions[:, None])[:, 0]
        actions_np, log_probs, values = actions.cpu().numpy(), log_probs.cpu().numpy(), self._denormalise(values)
        logits = logits.cpu().numpy()
        for j, column in enumerate([] if columns is None else np.asarray(columns).tolist()):
            pending = self._column_cache.setdefault(column, collections.deque(maxlen=2))
            pending.append((int(actions_np[j]), float(log_probs[j]), float(values[j]), logits[j]))
        return actions_np

    def observe_batch(self, obs, actions, rewards, next_obs, terminated, truncated, columns) -> None:
        columns = np.asarray(columns).tolist()
        self.buffer.ensure_capacity(self.buffer.pos + len(columns))
        cached = [self._column_cache[c].popleft() if self._column_cache.get(c) else None for c in columns]
        missing = [j for j, (c, a) in enumerate(zip(cached, actions, strict=True)) if c is None or c[0] != int(a)]
        if missing:  # not from our last act_batch: score them now
            with torch.no_grad():
                logits, values = self.net(obs_to_tensor(observations.take(obs, missing), self.device))
            log_probs, values = torch.log_softmax(logits, -1), self._denormalise(values)
            for row, j in enumerate(missing):
                a = int(actions[j])
                cached[j] = (a, log_probs[row, a].item(), values[row].item(), logits[row].cpu().numpy())
        bootstrap = []
        for j, column in enumerate(columns):
            _, log_prob, value, logits = cached[j]
            term, trunc = bool(terminated[j]), bool(truncated[j])
            t = self.buffer.add(observations.take(obs, j), int(actions[j]), log_prob, value,
                                float(rewards[j]) * self.config.reward_scale, term, trunc, logits, column=column)
            self.steps += 1
            if trunc and not term:
                bootstrap.append((t, j))
            if term or trunc:
                self._column_next.pop(column, None)
            else:
                self._column_next[column] = observations.copy(observations.take(next_obs, j))
        if bootstrap:  # time limit, not a real end: bootstrap from the final observations, one pass
            values = self._values(observations.stack([observations.take(next_obs, j) for _, j in bootstrap]))
            for (t, _), v in zip(bootstrap, values, strict=True):
                self.buffer.next_values[t] = v

    @torch.no_grad()
    def _values(self, obs) -> np.ndarray:
        return self._denormalise(self.net(obs_to_tensor(obs, self.device))[1])

    def _denormalise(self, values: torch.Tensor) -> np.ndarray:
        """The value head's outputs as values (numpy): as they are, or with ``value_norm`` times
        the returns' running standard deviation plus their mean."""
        values = values.cpu().numpy()
        if not self.value_norm:
            return values
        return (values * np.float32(self.value_stats.std) + np.float32(self.value_stats.mean)).astype(np.float32)

    # ---- learning ---------------------------------------------------------------------
    def update(self) -> dict[str, float]:
        if not self.buffer.full:
            return {}
        cfg, buf = self.config, self.buffer
        n = buf.pos
        # Each environment's last transition, if its episode goes on, bootstraps from V(next obs).
        going_on = sorted(self._column_next)
        last_values = (self._values(observations.stack([self._column_next[c] for c in going_on]))
                       if going_on else [])
        next_values = buf.bootstrap_columns(dict(zip(going_on, np.asarray(last_values).tolist(), strict=True)))
        self._column_next.clear()
        advantages, returns = np.zeros(n, np.float32), np.zeros(n, np.float32)
        for idx in buf.column_indices():  # GAE along each environment's own sequence
            advantages[idx], returns[idx] = gae(
                buf.rewards[idx], buf.values[idx], next_values[idx], buf.terminateds[idx], buf.truncateds[idx],
                cfg.gamma, cfg.gae_lambda,
            )
        b_obs = obs_to_tensor(observations.take(buf.obs, slice(n)), self.device)
        b_actions = torch.as_tensor(buf.actions[:n], device=self.device)
        b_log_probs = torch.as_tensor(buf.log_probs[:n], device=self.device)
        b_logits = torch.as_tensor(buf.logits[:n], device=self.device)
        b_advantages = torch.as_tensor(advantages, device=self.device)
        if self.value_norm:  # the value head learns the returns in units of their running statistics
            self.value_stats.update(returns)
            targets = ((returns - self.value_stats.mean) / self.value_stats.std).astype(np.float32)
        else:
            targets = returns
        b_returns = torch.as_tensor(targets, device=self.device)

        for _epoch in range(cfg.epochs):
            epoch_stats: list[list[float]] = []
            for mb in np.array_split(self.rng.permutation(n), max(1, n // cfg.batch_size)):
                mb = torch.as_tensor(mb, device=self.device)
                epoch_stats.append(
                    self._minibatch_step(
                        observations.take(b_obs, mb), b_actions[mb], b_log_probs[mb], b_logits[mb],
                        b_advantages[mb], b_returns[mb],
                    )
                )
        pg_loss, v_loss, entropy, kl, clipfrac = np.mean(epoch_stats, axis=0)

        # Adaptive KL coefficient, RLlib's rule, from the last epoch's mean KL.
        if kl > 2.0 * cfg.kl_target:
            self.kl_coef *= 1.5
        elif kl < 0.5 * cfg.kl_target:
            self.kl_coef *= 0.5
        self.iterations += 1
        self.buffer.reset()
        explained_var = 1.0 - np.var(returns - buf.values[:n]) / max(np.var(returns), 1e-8)
        return {
            "losses/pg_loss": float(pg_loss),
            "losses/v_loss": float(v_loss),
            "losses/entropy": float(entropy),
            "losses/kl": float(kl),
            "losses/clipfrac": float(clipfrac),
            "losses/explained_variance": float(explained_var),
            "charts/kl_coef": float(self.kl_coef),
            "charts/iterations": float(self.iterations),
        }

    def losses(self, obs, actions, old_log_probs, old_logits, advantages, returns) -> dict[str, torch.Tensor]:
        """The terms of the loss on one minibatch (``returns``: the value targets, normalised
        with ``value_norm``): ``pg_loss``, ``kl``, ``v_loss``, ``entropy``, the probability
        ``ratio`` and ``loss`` = pg_loss + kl_coef kl + vf_coef v_loss - ent_coef entropy
        (bench/ppo_gradient_ratio.py takes each term's gradient on the shared encoder)."""
        cfg = self.config
        logits, values = self.net(obs, value_grad=cfg.shared_value_grad)
        dist = Categorical(logits=logits)
        log_probs = dist.log_prob(actions)
        ratio = torch.exp(log_probs - old_log_probs)
        # Exact KL(old || new) of the categorical policies, as RLlib's penalty uses.
        kl = kl_divergence(Categorical(logits=old_logits), dist).mean()
        if cfg.norm_adv and len(advantages) > 1:
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)

        pg_loss = torch.max(
            -advantages * ratio, -advantages * torch.clamp(ratio, 1 - cfg.clip_coef, 1 + cfg.clip_coef)
        ).mean()
        v_loss = 0.5 * ((values - returns) ** 2).mean()
        entropy = dist.entropy().mean()
        loss = pg_loss + self.kl_coef * kl + cfg.vf_coef * v_loss - cfg.ent_coef * entropy
        return {"pg_loss": pg_loss, "kl": kl, "v_loss": v_loss, "entropy": entropy, "ratio": ratio, "loss": loss}

    def _minibatch_step(self, obs, actions, old_log_probs, old_logits, advantages, returns) -> list[float]:
        cfg = self.config
        terms = self.losses(obs, actions, old_log_probs, old_logits, advantages, returns)
        self.optimizer.zero_grad()
        terms["loss"].backward()
        nn.utils.clip_grad_norm_(self.net.parameters(), cfg.max_grad_norm)
        self.optimizer.step()
        clipfrac = ((terms["ratio"] - 1.0).abs() > cfg.clip_coef).float().mean()
        return [terms[k].item() for k in ("pg_loss", "v_loss", "entropy", "kl")] + [clipfrac.item()]

    # ---- checkpoint extras ------------------------------------------------------------
    def _extra_state(self) -> dict[str, Any]:
        extra = {"kl_coef": float(self.kl_coef), "iterations": self.iterations, "steps": self.steps}
        if self.value_norm:
            extra["value_stats"] = self.value_stats.state()
        return extra

    def _load_extra_state(self, state) -> None:
        self.kl_coef = float(state.get("kl_coef", self.config.kl_coef))
        self.iterations = int(state.get("iterations", 0))
        self.steps = int(state.get("steps", 0))
        if "value_stats" in state:
            self.value_stats.load(state["value_stats"])


class RunningMeanStd:
    """Running mean and variance of a stream of numbers (float64; the parallel algorithm of Chan
    et al. 1979, as SB3's ``RunningMeanStd``), starting at mean 0, variance 1: PPO's
    ``value_norm`` statistics of the returns."""

    def __init__(self, epsilon: float = 1e-4):
        self.mean, self.var, self.count = 0.0, 1.0, float(epsilon)

    @property
    def std(self) -> float:
        """sqrt(var), at least 1e-8 (a constant stream)."""
        return max(float(np.sqrt(self.var)), 1e-8)

    def update(self, values) -> None:
        values = np.asarray(values, np.float64)
        if not values.size:
            return
        batch_mean, batch_var, n = float(values.mean()), float(values.var()), float(values.size)
        delta, total = batch_mean - self.mean, self.count + n
        m2 = self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        self.mean, self.var, self.count = self.mean + delta * n / total, m2 / total, total

    def state(self) -> dict[str, float]:
        return {"mean": float(self.mean), "var": float(self.var), "count": float(self.count)}

    def load(self, state) -> None:
        self.mean, self.var, self.count = (float(state[k]) for k in ("mean", "var", "count"))
