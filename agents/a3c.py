"""A3C: asynchronous advantage actor-critic (Mnih et al. 2016, arXiv:1602.01783).

Two ways to run the same algorithm:

* **Asynchronous** (:func:`train_a3c`), the real thing: N worker processes,
  each with its own environment and a local copy of the network, run n-step
  rollouts, compute gradients locally, write them into the *shared* model's
  ``.grad`` and step a *shared* Adam (its moments live in shared memory too,
  as in ikostrikov/pytorch-a3c), lock-free ("Hogwild", Recht et al. 2011).
  One shared model per agent id: the driving benchmark trains N cars, each
  with its own network, all A3C.
* **In-process** (:class:`A3C` through the :class:`~agents.base.Agent`
  interface): n-step advantage actor-critic on the caller's own transitions.
  This is how a trained policy acts in the test protocol, and how the common
  loop and the smoke tests drive it.

Loss per rollout (means over the T steps; RLlib 0.8, which the paper used,
sums, so the paper's lr is not directly comparable):
``pg_loss = -mean(A_t log pi(a_t|s_t))``, ``v_loss = 0.5 mean((R_t - V(s_t))^2)``,
``loss = pg_loss + vf_coef v_loss - ent_coef H[pi]``, with ``A_t, R_t`` from GAE
(lambda 1.0 = the n-step returns of the A3C paper), and the global gradient
norm clipped before the shared step.
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
from agents.returns import gae
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

__all__ = ["A3C", "A3CConfig", "SharedAdam", "a3c_loss", "train_a3c"]

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- config


@dataclasses.dataclass(frozen=True)
class A3CConfig(AgentConfig):
    """A3C hyperparameters. ``preset("paper")`` is the paper's Table 3."""

    learning_rate: float = 1e-3
    """Adam step size of the shared optimizer."""
    gamma: float = 0.99
    """Discount factor."""
    gae_lambda: float = 1.0
    """GAE lambda; 1.0 gives the plain n-step returns of the A3C paper."""
    n_steps: int = 20
    """Env steps per worker rollout between two updates (the n of n-step returns)."""
    vf_coef: float = 0.5
    """Weight of the value loss."""
    ent_coef: float = 0.01
    """Weight of the entropy bonus."""
    max_grad_norm: float = 0.5
    """Global gradient-norm clip applied by each worker before its shared step."""
    adam_eps: float = 1e-5
    """Adam epsilon."""
    anneal_lr: bool = True
    """Decay the learning rate linearly to 0 over ``total_steps`` (asynchronous training only)."""
    hidden: tuple[int, ...] = (64, 64)
    """Hidden sizes of the MLP encoder (image observations use the Nature CNN)."""

    PRESETS: ClassVar = {
        "default": {},
        # Table 3 of the paper; n_steps 10 is RLlib 0.8's A3C rollout length,
        # which the paper did not change.
        "paper": {
            "learning_rate": 5e-3,
            "vf_coef": 1.0,
            "ent_coef": 0.01,
            "gae_lambda": 1.0,
            "max_grad_norm": 30.0,
            "gamma": 0.99,
            "n_steps": 10,
            "adam_eps": 1e-8,
            "anneal_lr": False,
        },
    }

    def __post_init__(self):
        super().__post_init__()
        check_range("learning_rate", self.learning_rate, 0.0, low_inclusive=False)
        check_range("gamma", self.gamma, 0.0, 1.0)
        check_range("gae_lambda", self.gae_lambda, 0.0, 1.0)
        check_range("n_steps", self.n_steps, 1)
        check_range("vf_coef", self.vf_coef, 0.0)
        check_range("ent_coef", self.ent_coef, 0.0)
        check_range("max_grad_norm", self.max_grad_norm, 0.0, low_inclusive=False)
        check_range("adam_eps", self.adam_eps, 0.0, low_inclusive=False)
        if not self.hidden or any(int(h) < 1 for h in self.hidden):
            raise ValueError(f"hidden={self.hidden!r} must be a non-empty tuple of positive sizes")


# ----------------------------------------------------------------------------- shared optimizer


class SharedAdam(torch.optim.Adam):
    """Adam whose moment estimates can live in shared memory.

    The state is created eagerly (plain Adam creates it on the first step,
    inside one process) so :meth:`share_memory` can move it to shared memory
    before the workers start; every worker then steps the same moments
    (ikostrikov/pytorch-a3c ``my_optim.py``).
    """

    def __init__(self, params, lr: float = 1e-3, eps: float = 1e-8):
        # foreach=False: the single-tensor path updates each state tensor in
        # place, which is what makes a shared-memory state work.
        super().__init__(params, lr=lr, eps=eps, foreach=False)
        for group in self.param_groups:
            for p in group["params"]:
                state = self.state[p]
                state["step"] = torch.zeros((), dtype=torch.float32)
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)

    def share_memory(self) -> SharedAdam:
        """Move every state tensor to shared memory; returns self."""
        for state in self.state.values():
            for value in state.values():
                if torch.is_tensor(value):
                    value.share_memory_()
        return self


# ----------------------------------------------------------------------------- loss


def a3c_loss(model: nn.Module, rollout: Rollout, config: A3CConfig) -> tuple[torch.Tensor, dict[str, float]]:
    """The A3C loss on one rollout of one agent.

    Args:
        model: ``ActorCritic`` giving ``(logits, values)``.
        rollout: Consecutive transitions of one agent.
        config: Supplies gamma, lambda and the loss weights.

    Returns:
        ``(loss, metrics)``; ``loss`` carries gradients to ``model``.
    """
    device = next(model.parameters()).device
    logits, values = model(obs_to_tensor(rollout.obs, device))

    def value_fn(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(obs_to_tensor(obs, device))[1].cpu().numpy()

    values_np = values.detach().cpu().numpy()
    next_values = rollout.next_values(values_np, value_fn)
    # A rollout boundary that is not a termination acts like a truncation:
    # bootstrap from the next value, do not look past it.
    advantages, returns = gae(
        rollout.rewards, values_np, next_values, rollout.terminateds,
        rollout.boundaries & ~rollout.terminateds, config.gamma, config.gae_lambda,
    )
    advantages = torch.as_tensor(advantages, device=device)
    returns = torch.as_tensor(returns, device=device)

    log_probs_all = torch.log_softmax(logits, dim=-1)
    actions = torch.as_tensor(rollout.actions, device=device)
    log_probs = log_probs_all.gather(1, actions[:, None]).squeeze(1)
    entropy = -(log_probs_all.exp() * log_probs_all).sum(-1).mean()

    pg_loss = -(advantages * log_probs).mean()
    v_loss = 0.5 * (returns - values).pow(2).mean()
    loss = pg_loss + config.vf_coef * v_loss - config.ent_coef * entropy
    metrics = {
        "losses/policy_loss": pg_loss.item(),
        "losses/value_loss": v_loss.item(),
        "losses/entropy": entropy.item(),
    }
    return loss, metrics


def compute_gradients(model: nn.Module, rollout: Rollout, config: A3CConfig) -> dict[str, float]:
    """Backpropagate the A3C loss into ``model``'s ``.grad`` and clip it."""
    loss, metrics = a3c_loss(model, rollout, config)
    model.zero_grad(set_to_none=True)
    loss.backward()
    grad_norm = nn.utils.clip_grad_norm_(model.parameters(), config.max_grad_norm)
    metrics["losses/grad_norm"] = float(grad_norm)
    return metrics


# ----------------------------------------------------------------------------- agent


class A3C(Agent):
    """A3C agent: acts on one observation; learns in-process as n-step A2C.

    Attributes:
        model: The ``ActorCritic`` network (shared-memory after :func:`train_a3c`).
        optimizer: Its :class:`SharedAdam`.
    """

    algo: ClassVar[str] = "a3c"
    config_class: ClassVar[type[AgentConfig]] = A3CConfig

    @classmethod
    def check_spaces(cls, observation_space: gymnasium.Space, action_space: gymnasium.Space) -> None:
        if not isinstance(action_space, gymnasium.spaces.Discrete):
            raise ValueError(
                f"A3C here supports Discrete action spaces only, got {action_space!r}; "
                "use DDPG or TD3 for the continuous driving actions"
            )
        if not isinstance(observation_space, gymnasium.spaces.Box):
            raise ValueError(f"A3C needs a Box observation space, got {observation_space!r}")

    def _build(self) -> None:
        config: A3CConfig = self.config
        self.model = ActorCritic(self.observation_space, int(self.action_space.n), config.hidden).to(self.device)
        self.optimizer = SharedAdam(self.model.parameters(), lr=config.learning_rate, eps=config.adam_eps)
        self.networks = {"actor_critic": self.model}
        self.optimizers = {"adam": self.optimizer}
        self._builder = RolloutBuilder("self")
        self.num_updates = 0

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> int:
        logits, _ = self.model(self.obs_batch(obs))
        if deterministic:
            return int(logits[0].argmax())
        # Sampled on the model's device with the agent's own generator (same device).
        probs = torch.softmax(logits[0], dim=-1)
        return int(torch.multinomial(probs, 1, generator=self.generator))

    def observe(self, obs, action, reward: float, next_obs, terminated: bool, truncated: bool) -> None:
        self._builder.add(obs, action, reward * self.config.reward_scale, next_obs, terminated, truncated)

    def update(self) -> dict[str, float]:
        if len(self._builder) < self.config.n_steps:
            return {}
        metrics = compute_gradients(self.model, self._builder.build(), self.config)
        self.optimizer.step()
        self.num_updates += 1
        metrics["charts/num_updates"] = float(self.num_updates)
        return metrics

    def _extra_state(self) -> dict[str, Any]:
        return {"num_updates": self.num_updates}

    def _load_extra_state(self, state) -> None:
        self.num_updates = int(state.get("num_updates", 0))


# ----------------------------------------------------------------------------- asynchronous training


def _a3c_worker(
    link: WorkerLink,
    env_fn: Callable[[], Any],
    agent_ids: list[str],
    config: A3CConfig,
    shared_models: dict[str, nn.Module],
    optimizers: dict[str, SharedAdam],
    global_steps,
    total_steps: int,
    seed: int,
) -> None:
    """One actor-learner: its own env, local models, Hogwild updates of the shared ones."""
    torch.manual_seed(seed)
    env = make_parallel_env(env_fn)
    try:
        runner = EnvRunner(env, agent_ids, seed=seed, worker=link.index, reward_scale=config.reward_scale)
        local_models = {aid: private_copy(shared_models[aid]) for aid in agent_ids}
        generator = torch.Generator().manual_seed(seed)
        policies = {aid: categorical_policy(local_models[aid], generator) for aid in agent_ids}
        while not link.should_stop() and global_steps.value < total_steps:
            for aid in agent_ids:  # 1. sync the local copy with the shared weights
                local_models[aid].load_state_dict(shared_models[aid].state_dict())
            rollouts, episodes, env_steps = runner.collect(policies, config.n_steps)  # 2. act
            with global_steps.get_lock():
                global_steps.value += env_steps
            metrics: dict[str, dict[str, float]] = {}
            for aid, rollout in rollouts.items():  # 3. local gradients -> shared step
                metrics[aid] = compute_gradients(local_models[aid], rollout, config)
                for local_p, shared_p in zip(
                    local_models[aid].parameters(), shared_models[aid].parameters(), strict=True
                ):
                    shared_p.grad = local_p.grad
                if config.anneal_lr:
                    lr = linear_learning_rate(optimizers[aid], config.learning_rate, global_steps.value, total_steps)
                    metrics[aid]["charts/learning_rate"] = lr
                optimizers[aid].step()
            link.send((env_steps, episodes, metrics))
    finally:
        if hasattr(env, "close"):
            env.close()


def train_a3c(
    env_fn: Callable[[], Any],
    observation_space: gymnasium.Space,
    action_space: gymnasium.Space,
    agent_ids: Sequence[str] = ("agent_0",),
    config: A3CConfig | None = None,
    total_steps: int = 100_000,
    num_workers: int = 2,
    seed: int = 0,
    callback: Callable[[TrainProgress], bool | None] | None = None,
    start_method: str = "spawn",
    agents: dict[str, A3C] | None = None,
) -> dict[str, A3C]:
    """Train one A3C agent per agent id with asynchronous worker processes.

    Args:
        env_fn: Picklable zero-argument factory; each worker calls it once to
            build its own env (a ParallelEnv, or a Gymnasium env for one agent).
        observation_space: Space of one agent's observation.
        action_space: Space of one agent's action (Discrete).
        agent_ids: The learning agents in the env; each gets its own network.
        config: Hyperparameters (default preset if None).
        total_steps: Env steps to take, all workers counted.
        num_workers: Number of actor-learner processes.
        seed: Seeds network init (agent k: ``seed + k``) and the workers' envs.
        callback: Called in the parent after each worker report with a
            :class:`TrainProgress`; return True to stop early
            (as in :func:`agents.loop.run_loop`).
        start_method: ``"spawn"`` or ``"forkserver"``.
        agents: Agents to continue training (e.g. loaded from checkpoints to resume);
            default: fresh agents built from ``config`` and ``seed``.

    Returns:
        Agent id -> trained :class:`A3C` agent, ready to act or save.

    Raises:
        WorkerError: If a worker raised (with its traceback) or died.
        KeyboardInterrupt: On Ctrl-C/SIGTERM; every worker is stopped first.
    """
    config = config if config is not None else A3CConfig()
    agent_ids = list(agent_ids)
    if num_workers < 1 or total_steps < 1:
        raise ValueError(f"need num_workers >= 1 and total_steps >= 1, got {num_workers}, {total_steps}")
    agents = agents_for(A3C, observation_space, action_space, agent_ids, config, seed, agents)
    shared_models = {aid: agent.model.share_memory() for aid, agent in agents.items()}
    optimizers = {aid: agent.optimizer.share_memory() for aid, agent in agents.items()}

    # torch.optim imports torch._dynamo on first use (~2 s); with a fork server
    # it is imported once there instead of once per worker.
    context = get_context(start_method, preload=[__name__, "torch._dynamo"])
    global_steps = context.Value("q", 0)
    worker_args = [
        (env_fn, agent_ids, config, shared_models, optimizers, global_steps, total_steps, worker_seed(seed, i))
        for i in range(num_workers)
    ]
    start = time.monotonic()
    recent_returns: deque[float] = deque(maxlen=100)
    with WorkerPool(_a3c_worker, worker_args, context=context) as pool:
        logger.info("A3C: %d workers (pids %s), %d steps", num_workers, pool.pids, total_steps)
        # Workers stop themselves once the shared step counter reaches total_steps;
        # reports still in the queue after they exit are read before leaving.
        while True:
            report = pool.get(timeout=0.5)
            if report is None:
                if pool.all_exited():
                    break
                continue
            _, episodes, metrics = report
            for aid in metrics:  # the parent's agents count the shared updates
                agents[aid].num_updates += 1
            for episode in episodes:
                recent_returns.extend(episode.returns.values())
            if episodes:
                logger.debug("A3C: %d steps, mean return (last 100) %.1f", global_steps.value, np.mean(recent_returns))
            progress = TrainProgress(
                int(global_steps.value), episodes, agents, pool.pids, time.monotonic() - start, metrics
            )
            if callback is not None and callback(progress):
                logger.info("A3C: callback stopped training at %d steps", progress.env_steps)
                break
        pool.check()
    logger.info("A3C: done, %d env steps in %.1f s", global_steps.value, time.monotonic() - start)
    return agents
