"""IMPALA: importance-weighted actor-learner architecture (Espeholt et al. 2018, arXiv:1802.01561).

Two ways to run the same algorithm:

* **Asynchronous** (:func:`train_impala`), the real thing: actor processes,
  each with its own environment and a possibly stale copy of the policy
  (pulled from shared memory every ``actor_sync_every`` unrolls), send
  trajectories (obs, actions, rewards, dones, behaviour log-probs) through a
  queue to ONE learner in the parent. The learner batches ``batch_size``
  unrolls per agent, corrects the off-policy gap with V-trace
  (:func:`agents.returns.vtrace`), takes an Adam step and publishes the new
  weights. One learner network per agent id (the driving benchmark trains N
  cars, each with its own network, all IMPALA).
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

import dataclasses
import logging
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import gymnasium
import numpy as np
import torch
from torch import nn

from agents.base import Agent, AgentConfig, check_range
from agents.networks import ActorCritic, obs_to_tensor
from agents.returns import vtrace
from agents.workers import (
    EnvRunner,
    Rollout,
    RolloutBuilder,
    TrainProgress,
    WorkerLink,
    WorkerPool,
    agents_for,
    categorical_policy,
    get_context,
    linear_learning_rate,
    make_parallel_env,
    private_copy,
    worker_seed,
)

__all__ = ["IMPALA", "IMPALAConfig", "impala_loss", "train_impala"]

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- config


@dataclasses.dataclass(frozen=True)
class IMPALAConfig(AgentConfig):
    """IMPALA hyperparameters. ``preset("paper")`` is the paper's Table 3."""

    learning_rate: float = 1e-3
    """Adam step size of the learner."""
    gamma: float = 0.99
    """Discount factor."""
    unroll_length: int = 20
    """Env steps per actor trajectory (the T of V-trace)."""
    batch_size: int = 4
    """Trajectories per agent in one learner update."""
    vf_coef: float = 0.5
    """Weight of the value (baseline) loss."""
    ent_coef: float = 0.01
    """Weight of the entropy bonus."""
    rho_bar: float = 1.0
    """V-trace truncation of the importance weights (rho-bar)."""
    c_bar: float = 1.0
    """V-trace truncation of the trace coefficients (c-bar)."""
    max_grad_norm: float = 0.5
    """Global gradient-norm clip of the learner."""
    adam_eps: float = 1e-5
    """Adam epsilon."""
    anneal_lr: bool = True
    """Decay the learning rate linearly to 0 over ``total_steps`` (asynchronous training only)."""
    actor_sync_every: int = 1
    """Actors pull the learner's latest weights every this many unrolls."""
    queue_size: int = 32
    """Bound on trajectories waiting for the learner; full = actors wait (bounds staleness)."""
    hidden: tuple[int, ...] = (64, 64)
    """Hidden sizes of the MLP encoder (image observations use the Nature CNN)."""

    PRESETS: ClassVar = {
        "default": {},
        # Table 3 of the paper; unroll 50 x batch 10 (500 steps per update) are
        # RLlib 0.8's IMPALA defaults, which the paper did not change.
        "paper": {
            "learning_rate": 1e-4,
            "vf_coef": 0.5,
            "ent_coef": 0.01,
            "rho_bar": 1.0,
            "c_bar": 1.0,
            "max_grad_norm": 30.0,
            "gamma": 0.99,
            "unroll_length": 50,
            "batch_size": 10,
            "adam_eps": 1e-8,
            "anneal_lr": False,
        },
    }

    def __post_init__(self):
        super().__post_init__()
        check_range("learning_rate", self.learning_rate, 0.0, low_inclusive=False)
        check_range("gamma", self.gamma, 0.0, 1.0)
        check_range("unroll_length", self.unroll_length, 1)
        check_range("batch_size", self.batch_size, 1)
        check_range("vf_coef", self.vf_coef, 0.0)
        check_range("ent_coef", self.ent_coef, 0.0)
        check_range("rho_bar", self.rho_bar, 0.0, low_inclusive=False)
        check_range("c_bar", self.c_bar, 0.0, low_inclusive=False)
        check_range("max_grad_norm", self.max_grad_norm, 0.0, low_inclusive=False)
        check_range("adam_eps", self.adam_eps, 0.0, low_inclusive=False)
        check_range("actor_sync_every", self.actor_sync_every, 1)
        check_range("queue_size", self.queue_size, 1)
        if not self.hidden or any(int(h) < 1 for h in self.hidden):
            raise ValueError(f"hidden={self.hidden!r} must be a non-empty tuple of positive sizes")


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

    algo: ClassVar[str] = "impala"
    config_class: ClassVar[type[AgentConfig]] = IMPALAConfig

    @classmethod
    def check_spaces(cls, observation_space: gymnasium.Space, action_space: gymnasium.Space) -> None:
        if not isinstance(action_space, gymnasium.spaces.Discrete):
            raise ValueError(
                f"IMPALA here supports Discrete action spaces only, got {action_space!r}; "
                "use DDPG or TD3 for the continuous driving actions"
            )
        if not isinstance(observation_space, gymnasium.spaces.Box):
            raise ValueError(f"IMPALA needs a Box observation space, got {observation_space!r}")

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


# ----------------------------------------------------------------------------- asynchronous training


def _impala_actor(
    link: WorkerLink,
    env_fn: Callable[[], Any],
    agent_ids: list[str],
    config: IMPALAConfig,
    published: dict[str, nn.Module],
    policy_version,
    seed: int,
) -> None:
    """One actor: its own env and policy copy; ships trajectories to the learner."""
    torch.manual_seed(seed)
    env = make_parallel_env(env_fn)
    try:
        runner = EnvRunner(env, agent_ids, seed=seed, worker=link.index, reward_scale=config.reward_scale)
        local_models = {aid: private_copy(published[aid]) for aid in agent_ids}
        generator = torch.Generator().manual_seed(seed)
        policies = {aid: categorical_policy(local_models[aid], generator) for aid in agent_ids}
        local_version, unrolls = -1, 0
        while not link.should_stop():
            if unrolls % config.actor_sync_every == 0 and policy_version.value != local_version:
                # The lock keeps us from reading weights the learner is half-way through writing.
                with policy_version.get_lock():
                    for aid in agent_ids:
                        local_models[aid].load_state_dict(published[aid].state_dict())
                    local_version = policy_version.value
            rollouts, episodes, env_steps = runner.collect(policies, config.unroll_length)
            unrolls += 1
            if not link.send((rollouts, episodes, env_steps, local_version)):
                break
    finally:
        if hasattr(env, "close"):
            env.close()


def _publish(agents: dict[str, IMPALA], published: dict[str, nn.Module], policy_version) -> None:
    """Copy the learner weights to the actors' shared copies, atomically for readers."""
    with policy_version.get_lock():
        for aid, agent in agents.items():
            published[aid].load_state_dict(agent.model.state_dict())
        policy_version.value += 1


def train_impala(
    env_fn: Callable[[], Any],
    observation_space: gymnasium.Space,
    action_space: gymnasium.Space,
    agent_ids: Sequence[str] = ("agent_0",),
    config: IMPALAConfig | None = None,
    total_steps: int = 100_000,
    num_actors: int = 2,
    seed: int = 0,
    callback: Callable[[TrainProgress], bool | None] | None = None,
    start_method: str = "spawn",
    agents: dict[str, IMPALA] | None = None,
) -> dict[str, IMPALA]:
    """Train one IMPALA agent per agent id: actor processes, one learner here.

    Args:
        env_fn: Picklable zero-argument factory; each actor calls it once to
            build its own env (a ParallelEnv, or a Gymnasium env for one agent).
        observation_space: Space of one agent's observation.
        action_space: Space of one agent's action (Discrete).
        agent_ids: The learning agents in the env; each gets its own network.
        config: Hyperparameters (default preset if None).
        total_steps: Env steps to take, all actors counted.
        num_actors: Number of actor processes.
        seed: Seeds network init (agent k: ``seed + k``) and the actors' envs.
        callback: Called after each received trajectory set with a
            :class:`TrainProgress`; return True to stop early
            (as in :func:`agents.loop.run_loop`).
        start_method: ``"spawn"`` or ``"forkserver"``.
        agents: Agents to continue training (e.g. loaded from checkpoints to resume);
            default: fresh agents built from ``config`` and ``seed``.

    Returns:
        Agent id -> trained :class:`IMPALA` agent, ready to act or save.

    Raises:
        WorkerError: If an actor raised (with its traceback) or died.
        KeyboardInterrupt: On Ctrl-C/SIGTERM; every actor is stopped first.
    """
    config = config if config is not None else IMPALAConfig()
    agent_ids = list(agent_ids)
    if num_actors < 1 or total_steps < 1:
        raise ValueError(f"need num_actors >= 1 and total_steps >= 1, got {num_actors}, {total_steps}")
    agents = agents_for(IMPALA, observation_space, action_space, agent_ids, config, seed, agents)
    # The actors read these copies, never the learner's own weights mid-update.
    published = {aid: private_copy(agent.model).share_memory() for aid, agent in agents.items()}

    context = get_context(start_method, preload=[__name__])
    policy_version = context.Value("q", 0)
    actor_args = [
        (env_fn, agent_ids, config, published, policy_version, worker_seed(seed, i))
        for i in range(num_actors)
    ]
    start = time.monotonic()
    env_steps, lags = 0, deque(maxlen=100)
    pending: dict[str, list[Rollout]] = {aid: [] for aid in agent_ids}
    with WorkerPool(_impala_actor, actor_args, context=context, queue_size=config.queue_size) as pool:
        logger.info("IMPALA: %d actors (pids %s), %d steps", num_actors, pool.pids, total_steps)
        while env_steps < total_steps:
            message = pool.get(timeout=0.5)
            if message is None:
                continue
            rollouts, episodes, steps, actor_version = message
            env_steps += steps
            lags.append(policy_version.value - actor_version)
            metrics: dict[str, dict[str, float]] = {}
            for aid, rollout in rollouts.items():
                pending[aid].append(rollout)
                if len(pending[aid]) >= config.batch_size:
                    if config.anneal_lr:
                        linear_learning_rate(agents[aid].optimizer, config.learning_rate, env_steps, total_steps)
                    metrics[aid] = agents[aid].learn(pending[aid])
                    metrics[aid]["charts/learning_rate"] = agents[aid].optimizer.param_groups[0]["lr"]
                    # Weight publications the actors were behind, averaged over recent unrolls.
                    metrics[aid]["charts/policy_lag"] = float(np.mean(lags))
                    pending[aid] = []
                    _publish({aid: agents[aid]}, {aid: published[aid]}, policy_version)
            progress = TrainProgress(env_steps, episodes, agents, pool.pids, time.monotonic() - start, metrics)
            if callback is not None and callback(progress):
                logger.info("IMPALA: callback stopped training at %d steps", env_steps)
                break
    for agent in agents.values():  # in-process learning after this starts from the configured lr
        linear_learning_rate(agent.optimizer, config.learning_rate, 0, total_steps)
    logger.info("IMPALA: done, %d env steps in %.1f s", env_steps, time.monotonic() - start)
    return agents
