"""IMPALA: importance-weighted actor-learner architecture (Espeholt et al. 2018, arXiv:1802.01561).

Two ways to run the same algorithm:

* **Actor-learner** (:func:`train_impala`), the real thing: the learner
  (this process) drives ONE vector env of N environments (``agents/vector.py``,
  the code path every algorithm steps its environments through). It acts for
  each agent in all the envs of a group with one forward pass, keeps the
  behaviour log-probs ``log mu(a|x)``, cuts per-(env, agent) unrolls of
  ``unroll_length``, batches ``batch_size`` unrolls per agent and corrects the
  off-policy gap with V-trace (:func:`agents.returns.vtrace`). With worker
  processes the envs form two groups (double buffering): one steps while the
  learner acts and learns for the other. Either way the actions of a step are
  chosen before the learner learns from the previous one, so an unroll's first
  actions come from weights some updates older than the learner's
  (``charts/policy_lag``); V-trace corrects that gap. One learner network per agent id (the driving benchmark trains N cars,
  each with its own network, all IMPALA).
* **In-process** (:class:`IMPALA` through the :class:`~agents.base.Agent`
  interface): the same learner fed with the agent's own transitions. This is
  how a trained policy acts in the test protocol and how the smoke tests
  drive it.

Loss per batch (means over steps; RLlib 0.8, which the paper used, sums):
``pg_loss = -mean(rho_t (r_t + gamma v_{t+1} - V(x_t)) log pi(a_t|x_t))``,
``v_loss = 0.5 mean((v_t - V(x_t))^2)``,
``loss = pg_loss + vf_coef v_loss - ent_coef H[pi]``; gradient norm clipped.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import gymnasium
import numpy as np
import torch
from torch import nn

from agents.async_env import EpisodeTracker, Unrolls, act_for, check_agents, record, vector_env
from agents.base import Agent, check_observation_space
from agents.configs import AgentConfig, IMPALAConfig
from agents.networks import ActorCritic, obs_to_tensor
from agents.returns import vtrace
from agents.workers import (
    Rollout,
    RolloutBuilder,
    TrainProgress,
    agents_for,
    linear_learning_rate,
    rates,
)

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
    """IMPALA agent: acts on one observation; in-process it is the learner of its own data.

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
        self._builder = RolloutBuilder("self")
        self._pending: list[Rollout] = []
        self._last_action: tuple[int, float] | None = None  # (action, log mu) of the last act()
        self.num_updates = 0

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> int:
        logits, _ = self.model(self.obs_batch(obs))
        log_probs = torch.log_softmax(logits[0], dim=-1)
        if deterministic:
            action = int(log_probs.argmax())
        else:
            action = int(torch.multinomial(log_probs.exp(), 1, generator=self.generator))
        self._last_action = (action, float(log_probs[action]))
        return action

    def observe(self, obs, action, reward: float, next_obs, terminated: bool, truncated: bool) -> None:
        # V-trace needs log mu(a|x) of the policy that acted; act() cached it.
        if self._last_action is not None and self._last_action[0] == int(action):
            behaviour_log_prob = self._last_action[1]
        else:  # the caller acted on its own: score its action under our policy
            with torch.no_grad():
                logits, _ = self.model(self.obs_batch(obs))
            behaviour_log_prob = float(torch.log_softmax(logits[0], dim=-1)[int(action)])
        self._last_action = None
        self._builder.add(obs, action, reward * self.config.reward_scale, next_obs, terminated, truncated,
                          behaviour_log_prob)

    def update(self) -> dict[str, float]:
        if len(self._builder) >= self.config.unroll_length:
            self._pending.append(self._builder.build())
        if len(self._pending) < self.config.batch_size:
            return {}
        metrics = self.learn(self._pending)
        self._pending = []
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
    callback: Callable[[TrainProgress], bool | None] | None = None,
    start_method: str = "spawn",
    agents: dict[str, IMPALA] | None = None,
    processes: bool | None = None,
) -> dict[str, IMPALA]:
    """Train one IMPALA agent per agent id: the learner here acts in N environments of one vector env.

    Each vector step, every agent samples its actions in all the envs of a group
    with one forward pass and keeps ``log mu(a|x)``; the transitions of each
    (env, agent) are cut into unrolls of ``unroll_length``; ``batch_size`` unrolls
    of an agent make one V-trace update. With worker processes the envs form two
    groups: one steps while the learner acts and learns for the other, so
    actions lag the weights (reported as ``charts/policy_lag``, in updates);
    V-trace corrects that lag.

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
            with a :class:`TrainProgress`; return True to stop early.
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
    agent_ids = list(agent_ids)
    if total_steps < 1:
        raise ValueError(f"need total_steps >= 1, got {total_steps}")
    agents = agents_for(IMPALA, observation_space, action_space, agent_ids, config, seed, agents)
    models = {aid: agent.model for aid, agent in agents.items()}
    generators = {aid: agent.generator for aid, agent in agents.items()}
    start = time.monotonic()
    venv = vector_env(env_fn, num_envs, start_method, processes)
    try:
        check_agents(venv, agent_ids)
        n = venv.num_envs
        logger.info("IMPALA: %d environments (pids %s), %d steps", n, venv.pids, total_steps)
        groups = [np.asarray(g) for g in venv.groups]
        unrolls, tracker = Unrolls(), EpisodeTracker(venv.possible_agents, n)
        pending: dict[str, list[Rollout]] = {aid: [] for aid in agent_ids}
        lags: dict[str, list[int]] = {aid: [] for aid in agent_ids}

        def act_and_send(group: np.ndarray, state) -> tuple:
            acted, actions = act_for({a: models[a] for a in venv.possible_agents}, generators, group,
                                     state.obs, state.alive, n)
            venv.step_async(actions, group)
            return acted, {aid: agents[aid].num_updates for aid in agent_ids}

        loop_start = time.perf_counter()
        state = venv.reset(seed=seed)
        in_flight: dict[int, tuple] = {}
        sent = env_steps = agent_steps = 0
        for gi, group in enumerate(groups):
            if sent < total_steps:
                in_flight[gi] = act_and_send(group, state)
                sent += group.size
        stopping, gi = False, 0
        while in_flight:
            if gi not in in_flight:
                gi = (gi + 1) % len(groups)
                continue
            group, (acted, versions) = groups[gi], in_flight.pop(gi)
            state = venv.step_wait(group)
            env_steps += group.size
            agent_steps += record(unrolls, acted, state, config.reward_scale, versions)
            episodes = tracker.record(state, group)
            if not stopping and sent < total_steps:  # act before learning: the lag V-trace corrects
                in_flight[gi] = act_and_send(group, state)
                sent += group.size
            metrics = _learn_ready(agents, unrolls, pending, lags, config, env_steps, total_steps)
            progress = TrainProgress(env_steps, episodes, agents, venv.pids, time.monotonic() - start, metrics,
                                     rates(env_steps, agent_steps, loop_start))
            if callback is not None and callback(progress) and not stopping:
                logger.info("IMPALA: callback stopped training at %d steps", env_steps)
                stopping = True
            gi = (gi + 1) % len(groups)
    finally:
        venv.close()
        for agent in agents.values():  # in-process learning after this starts from the configured lr
            linear_learning_rate(agent.optimizer, config.learning_rate, 0, total_steps)
    logger.info("IMPALA: done, %d env steps in %.1f s", env_steps, time.monotonic() - start)
    return agents


def _learn_ready(agents: dict[str, IMPALA], unrolls: Unrolls, pending: dict[str, list[Rollout]],
                 lags: dict[str, list[int]], config: IMPALAConfig, env_steps: int,
                 total_steps: int) -> dict[str, dict[str, float]]:
    """Move full unrolls to their agent's batch; one learner step per agent whose batch is full."""
    metrics: dict[str, dict[str, float]] = {}
    for aid, _env, rollout, version in unrolls.take_ready(config.unroll_length):
        pending[aid].append(rollout)
        lags[aid].append(agents[aid].num_updates - version)  # updates since the unroll's first action
        if len(pending[aid]) < config.batch_size:
            continue
        if config.anneal_lr:
            linear_learning_rate(agents[aid].optimizer, config.learning_rate, env_steps, total_steps)
        metrics[aid] = agents[aid].learn(pending[aid])
        metrics[aid]["charts/learning_rate"] = agents[aid].optimizer.param_groups[0]["lr"]
        metrics[aid]["charts/policy_lag"] = float(np.mean(lags[aid]))
        pending[aid], lags[aid] = [], []
    return metrics
