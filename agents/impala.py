"""IMPALA: importance-weighted actor-learner architecture (Espeholt et al. 2018, arXiv:1802.01561).

One algorithm on the one loop (:func:`agents.loop.run_loop`), its hooks the
batch pair and ``update``: ``act_batch`` acts for the agent in all the envs of
a group with one forward pass and keeps the behaviour log-probs
``log mu(a|x)``; ``observe_batch`` cuts per-env unrolls of ``unroll_length``;
``update`` batches ``batch_size`` unrolls and corrects the off-policy gap with
V-trace (:func:`agents.returns.vtrace`). :func:`train_impala` (``cosim train
--algo impala``) runs the loop on ONE vector env of N environments
(``agents/vector.py``): with worker processes the envs form two groups (double
buffering), one steps while the learner acts and learns for the other. Either
way the actions of a step are chosen before the learner learns from the
previous one, so an unroll's first actions come from weights some updates
older than the learner's (``charts/policy_lag``); V-trace corrects that gap.
One learner network per agent id (the driving benchmark trains N cars, each
with its own network, all IMPALA).

Loss per batch (means over steps; RLlib 0.8, which the paper used, sums):
``pg_loss = -mean(rho_t (r_t + gamma v_{t+1} - V(x_t)) log pi(a_t|x_t))``,
``v_loss = 0.5 mean((v_t - V(x_t))^2)``,
``loss = pg_loss + vf_coef v_loss - ent_coef H[pi]``; gradient norm clipped.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import gymnasium
import numpy as np
import torch
from torch import nn

from agents import observations
from agents.async_env import Unrolls, vector_env
from agents.base import Agent, check_observation_space
from agents.configs import AgentConfig, IMPALAConfig
from agents.loop import Progress, run_loop
from agents.networks import ActorCritic, obs_to_tensor
from agents.returns import vtrace
from agents.workers import Rollout, agents_for

__all__ = ["IMPALA", "IMPALAConfig", "impala_loss", "train_impala"]

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- loss


def impala_loss(model: nn.Module, batch: Rollout, config: IMPALAConfig) -> tuple[torch.Tensor, dict[str, float]]:
    """The IMPALA loss on a batch of one agent's trajectories, with V-trace targets.

    Args:
        model: The learner's ``ActorCritic``.
        batch: Trajectories (``Rollout.concat`` of several); ``batch.log_probs``
            are the behaviour policy's ``log mu(a_t|x_t)``.
        config: Supplies gamma, the V-trace thresholds and the loss weights.

    Returns:
        ``(loss, metrics)``; ``loss`` carries gradients to ``model``.
    """
    device = next(model.parameters()).device
    logits, values = model(obs_to_tensor(batch.obs, device))
    log_probs_all = torch.log_softmax(logits, dim=-1)
    actions = torch.as_tensor(batch.actions, device=device)
    target_log_probs = log_probs_all.gather(1, actions[:, None]).squeeze(1)
    entropy = -(log_probs_all.exp() * log_probs_all).sum(-1).mean()

    def value_fn(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(obs_to_tensor(obs, device))[1].cpu().numpy()

    values_np = values.detach().cpu().numpy()
    next_values = batch.next_values(values_np, value_fn)
    discounts = config.gamma * (~batch.terminateds).astype(np.float32)
    # Trajectory boundaries stop the V-trace recursion (they bootstrap instead).
    vs, pg_advantages = vtrace(
        batch.log_probs, target_log_probs.detach().cpu().numpy(), batch.rewards, values_np,
        next_values, discounts, rho_bar=config.rho_bar, c_bar=config.c_bar,
        episode_ends=batch.boundaries,
    )
    vs = torch.as_tensor(vs, device=device)
    pg_advantages = torch.as_tensor(pg_advantages, device=device)

    pg_loss = -(pg_advantages * target_log_probs).mean()
    v_loss = 0.5 * (vs - values).pow(2).mean()
    loss = pg_loss + config.vf_coef * v_loss - config.ent_coef * entropy
    rhos = np.exp(target_log_probs.detach().cpu().numpy() - batch.log_probs)
    metrics = {
        "losses/policy_loss": pg_loss.item(),
        "losses/value_loss": v_loss.item(),
        "losses/entropy": entropy.item(),
        "charts/mean_rho": float(rhos.mean()),
    }
    return loss, metrics


# ----------------------------------------------------------------------------- agent


class IMPALA(Agent):
    """IMPALA agent: the learner of the transitions it acted for, in every environment of the loop.

    Attributes:
        model: The learner's ``ActorCritic``.
        optimizer: Its Adam.
    """

    optimizer_learning_rates: ClassVar[dict[str, str]] = {"adam": "learning_rate"}

    algo: ClassVar[str] = "impala"
    config_class: ClassVar[type[AgentConfig]] = IMPALAConfig

    @classmethod
    def check_spaces(cls, observation_space: gymnasium.Space, action_space: gymnasium.Space) -> None:
        if not isinstance(action_space, gymnasium.spaces.Discrete):
            raise ValueError(
                f"IMPALA here supports Discrete action spaces only, got {action_space!r}; "
                "use DDPG or TD3 for the continuous driving actions"
            )
        check_observation_space(cls.algo, observation_space)

    def _build(self) -> None:
        config: IMPALAConfig = self.config
        self.model = ActorCritic(self.observation_space, int(self.action_space.n), config.hidden).to(self.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.learning_rate, eps=config.adam_eps)
        self.networks = {"actor_critic": self.model}
        self.optimizers = {"adam": self.optimizer}
        self._unrolls = Unrolls()  # per env, the unroll being cut
        # act_batch's (action, log mu, update count) per env, oldest first: the loop acts at
        # t + 1 before it observes t, so up to two are pending
        self._behaviour: dict[int, collections.deque] = {}
        self._pending: list[Rollout] = []  # full unrolls waiting for a batch
        self._lags: list[int] = []  # per pending unroll, learner updates since its first action
        self.num_updates = 0

    def acting_chain(self, deterministic: bool = False) -> tuple[nn.Module, ...]:
        return (self.model,)

    @torch.no_grad()
    def act_from(self, outputs, columns: np.ndarray | None, deterministic: bool = False) -> np.ndarray:
        logits, _ = outputs
        log_probs = torch.log_softmax(logits, dim=-1)
        if deterministic:
            chosen = log_probs.argmax(-1, keepdim=True)
        else:
            chosen = torch.multinomial(log_probs.exp(), 1, generator=self.generator)
        behaviour = log_probs.gather(1, chosen).squeeze(1).cpu().numpy().astype(np.float32)
        actions = chosen.squeeze(1).cpu().numpy().astype(np.int64)
        for j, column in enumerate([] if columns is None else np.asarray(columns).tolist()):
            pending = self._behaviour.setdefault(column, collections.deque(maxlen=2))
            pending.append((int(actions[j]), float(behaviour[j]), self.num_updates))
        return actions

    def prepare_envs(self, num_envs: int) -> None:
        self._behaviour.clear()  # nothing acted before (e.g. an evaluation) is waiting for observe

    def observe_batch(self, obs, actions, rewards, next_obs, terminated, truncated, columns) -> None:
        columns = np.asarray(columns).tolist()
        cached = [self._behaviour[c].popleft() if self._behaviour.get(c) else None for c in columns]
        missing = [j for j, c in enumerate(cached) if c is None or c[0] != int(actions[j])]
        if missing:  # V-trace needs log mu(a|x); the caller acted on its own: score under our policy
            with torch.no_grad():
                logits, _ = self.model(obs_to_tensor(observations.take(obs, missing), self.device))
            log_probs = torch.log_softmax(logits, dim=-1)
            for row, j in enumerate(missing):
                cached[j] = (int(actions[j]), float(log_probs[row, int(actions[j])]), self.num_updates)
        rewards = np.asarray(rewards, np.float32) * self.config.reward_scale
        for j, column in enumerate(columns):
            _, log_mu, version = cached[j]
            self._unrolls.add("self", column, observations.take(obs, j), actions[j], rewards[j],
                              observations.take(next_obs, j), terminated[j], truncated[j], log_mu, version)

    def update(self) -> dict[str, float]:
        """Move full unrolls to the batch; one learner step per ``batch_size`` of them."""
        config = self.config
        metrics: dict[str, float] = {}
        for _aid, _env, rollout, version in self._unrolls.take_ready(config.unroll_length):
            self._pending.append(rollout)
            self._lags.append(self.num_updates - version)  # updates since the unroll's first action
            if len(self._pending) < config.batch_size:
                continue
            if config.anneal_lr:
                for group in self.optimizer.param_groups:
                    group["lr"] = config.learning_rate * self.progress_remaining
            metrics = self.learn(self._pending)
            metrics["charts/learning_rate"] = self.optimizer.param_groups[0]["lr"]
            metrics["charts/policy_lag"] = float(np.mean(self._lags))
            self._pending, self._lags = [], []
        return metrics

    def learn(self, trajectories: Sequence[Rollout]) -> dict[str, float]:
        """One learner step on a batch of this agent's trajectories."""
        loss, metrics = impala_loss(self.model, Rollout.concat(trajectories), self.config)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(self.model.parameters(), self.config.max_grad_norm)
        self.optimizer.step()
        self.num_updates += 1
        metrics["losses/grad_norm"] = float(grad_norm)
        metrics["charts/num_updates"] = float(self.num_updates)
        return metrics

    def _extra_state(self) -> dict[str, Any]:
        return {"num_updates": self.num_updates}

    def _load_extra_state(self, state) -> None:
        self.num_updates = int(state.get("num_updates", 0))


# ----------------------------------------------------------------------------- actor-learner training


def train_impala(
    env_fn: Callable[[], Any] | Sequence[Callable[[], Any]],
    observation_space: gymnasium.Space,
    action_space: gymnasium.Space,
    agent_ids: Sequence[str] = ("agent_0",),
    config: IMPALAConfig | None = None,
    total_steps: int = 100_000,
    num_envs: int | None = None,
    seed: int = 0,
    callback: Callable[[Progress], bool | None] | None = None,
    start_method: str = "spawn",
    agents: dict[str, IMPALA] | None = None,
    processes: bool | None = None,
) -> dict[str, IMPALA]:
    """Train one IMPALA agent per agent id: the learner here acts in N environments of one vector env.

    :func:`agents.loop.run_loop` on the vector env of ``env_fn``: each vector step, every
    agent samples its actions in all the envs of a group with one forward pass and keeps
    ``log mu(a|x)``; the transitions of each env are cut into unrolls of ``unroll_length``;
    ``batch_size`` unrolls of an agent make one V-trace update. With worker processes the
    envs form two groups: one steps while the learner acts and learns for the other, so
    actions lag the weights (reported as ``charts/policy_lag``, in updates); V-trace
    corrects that lag.

    Args:
        env_fn: Picklable zero-argument factory (a ParallelEnv, or a Gymnasium env
            for one agent), or one factory per environment.
        observation_space: Space of one agent's observation.
        action_space: Space of one agent's action (Discrete).
        agent_ids: The learning agents in the env; each gets its own network.
        config: Hyperparameters (default preset if None).
        total_steps: Env steps to take, all environments counted.
        num_envs: Environments (default: 2, or one per factory in ``env_fn``).
        seed: Seeds network init (agent k: ``seed + k``) and the resets (env i,
            episode k: ``seed + i + k * N``). Same seed and N: same run.
        callback: Called after each group of envs stepped and was learnt from,
            with the loop's :class:`~agents.loop.Progress`; return True to stop early.
        start_method: ``"spawn"`` or ``"forkserver"`` for the env worker processes.
        agents: Agents to continue training (e.g. loaded from checkpoints to resume);
            default: fresh agents built from ``config`` and ``seed``.
        processes: Env worker processes (default: when N > 1) or in process.

    Returns:
        Agent id -> trained :class:`IMPALA` agent, ready to act or save.

    Raises:
        WorkerError: If an environment raised (:class:`~agents.vector.VectorEnvError`,
            with the worker's traceback) or its worker died.
        KeyboardInterrupt: On Ctrl-C/SIGTERM; every env worker is stopped first.
    """
    config = config if config is not None else IMPALAConfig()
    if total_steps < 1:
        raise ValueError(f"need total_steps >= 1, got {total_steps}")
    agents = agents_for(IMPALA, observation_space, action_space, list(agent_ids), config, seed, agents)
    venv = vector_env(env_fn, num_envs, start_method, processes)
    try:
        run_loop(agents, venv, total_steps, callback, seed=seed)
    finally:
        venv.close()
    return agents
