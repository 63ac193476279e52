"""A3C: asynchronous advantage actor-critic (Mnih et al. 2016, arXiv:1602.01783).

Two ways to run the same algorithm:

* **Asynchronous** (:func:`train_a3c`), the real thing: one actor-learner
  thread per environment of ONE vector env (``agents/vector.py``, the code
  path every algorithm steps its environments through; thread k owns env
  index k). Each thread keeps a local copy of the network, runs n-step
  segments, computes gradients locally and applies them to the *shared*
  network with a *shared* Adam, lock-free ("Hogwild", Recht et al. 2011;
  :meth:`SharedAdam.apply_gradients`). One shared model per agent id: the
  driving benchmark trains N cars, each with its own network, all A3C.
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

import logging
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import gymnasium
import numpy as np
import torch
from torch import nn

from agents.async_env import ThreadRun, run_threads, vector_env
from agents.base import Agent, check_observation_space
from agents.configs import A3CConfig, AgentConfig
from agents.networks import ActorCritic, obs_to_tensor
from agents.returns import gae
from agents.workers import Rollout, RolloutBuilder, TrainProgress, agents_for

__all__ = ["A3C", "A3CConfig", "SharedAdam", "a3c_loss", "train_a3c"]

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- shared optimizer


class SharedAdam(torch.optim.Adam):
    """Adam whose moment estimates are shared by A3C's learner threads.

    The state is created eagerly (plain Adam creates it on the first step) and
    :meth:`apply_gradients` steps it with gradients computed elsewhere (a
    thread's local copy of the network), so no thread ever writes another's
    ``.grad``: Hogwild (Recht et al. 2011), lock-free, as ikostrikov/pytorch-a3c
    does across processes. ``step()`` (in-process A3C) is plain Adam.
    """

    def __init__(self, params, lr: float = 1e-3, eps: float = 1e-8):
        # foreach=False: the single-tensor path, the one apply_gradients reproduces.
        super().__init__(params, lr=lr, eps=eps, foreach=False)
        for group in self.param_groups:
            for p in group["params"]:
                state = self.state[p]
                state["step"] = torch.zeros((), dtype=torch.float32)
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)

    @torch.no_grad()
    def apply_gradients(self, grads: Sequence[torch.Tensor | None], lr: float) -> None:
        """One Adam step of the parameters (in ``param_groups`` order) with ``grads`` and ``lr``.

        The same arithmetic as ``torch.optim.Adam.step`` (no weight decay, no
        amsgrad), in place on the shared parameters and moments; a ``None``
        gradient leaves its parameter alone.
        """
        params = [p for group in self.param_groups for p in group["params"]]
        if len(grads) != len(params):
            raise ValueError(f"apply_gradients got {len(grads)} gradients for {len(params)} parameters")
        beta1, beta2 = self.param_groups[0]["betas"]
        eps = self.param_groups[0]["eps"]
        for param, grad in zip(params, grads, strict=True):
            if grad is None:
                continue
            state = self.state[param]
            state["step"] += 1
            step = float(state["step"])
            state["exp_avg"].lerp_(grad, 1 - beta1)
            state["exp_avg_sq"].mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            denom = (state["exp_avg_sq"].sqrt() / (1 - beta2**step) ** 0.5).add_(eps)
            param.addcdiv_(state["exp_avg"], denom, value=-lr / (1 - beta1**step))


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
        model: The ``ActorCritic`` network (the one :func:`train_a3c`'s threads share).
        optimizer: Its :class:`SharedAdam`.
    """

    optimizer_learning_rates: ClassVar[dict[str, str]] = {"adam": "learning_rate"}

    algo: ClassVar[str] = "a3c"
    config_class: ClassVar[type[AgentConfig]] = A3CConfig

    @classmethod
    def check_spaces(cls, observation_space: gymnasium.Space, action_space: gymnasium.Space) -> None:
        if not isinstance(action_space, gymnasium.spaces.Discrete):
            raise ValueError(
                f"A3C here supports Discrete action spaces only, got {action_space!r}; "
                "use DDPG or TD3 for the continuous driving actions"
            )
        check_observation_space(cls.algo, observation_space)

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


def _segment_learner(config: A3CConfig):
    """How a learner thread learns from a segment: local gradients, then one lock-free shared step."""

    def learn(run: ThreadRun, aid: str, local: nn.Module, rollout: Rollout, done: int, seen: int) -> dict:
        lr = config.learning_rate * (max(0.0, 1.0 - done / run.total_steps) if config.anneal_lr else 1.0)
        metrics = compute_gradients(local, rollout, config)
        agent = run.agents[aid]
        agent.optimizer.apply_gradients([p.grad for p in local.parameters()], lr)
        with run.lock:
            agent.num_updates += 1
            # shared updates other threads applied since this segment's weights were read
            metrics["charts/staleness"] = float(agent.num_updates - 1 - seen)
        metrics["charts/learning_rate"] = lr
        return metrics

    return learn


def train_a3c(
    env_fn: Callable[[], Any] | Sequence[Callable[[], Any]],
    observation_space: gymnasium.Space,
    action_space: gymnasium.Space,
    agent_ids: Sequence[str] = ("agent_0",),
    config: A3CConfig | None = None,
    total_steps: int = 100_000,
    num_envs: int | None = None,
    seed: int = 0,
    callback: Callable[[TrainProgress], bool | None] | None = None,
    start_method: str = "spawn",
    agents: dict[str, A3C] | None = None,
    processes: bool | None = None,
) -> dict[str, A3C]:
    """Train one A3C agent per agent id: one actor-learner thread per environment of one vector env.

    Thread k owns env index k of the vector env (``agents/vector.py``; the env
    steps in its worker process, or in process for N = 1), keeps a local copy of
    each agent's network, runs n-step segments, and applies their gradients to
    the shared network with the shared Adam (:meth:`SharedAdam.apply_gradients`),
    lock-free, whenever it is done: asynchronous, as in the paper. Torch releases
    the GIL inside its ops and a thread waiting for its env holds no lock, so the
    threads overlap. Runs are not reproducible step for step for N > 1 (the order
    of the threads' updates varies); with N = 1 they are.

    Args:
        env_fn: Picklable zero-argument factory (a ParallelEnv, or a Gymnasium env
            for one agent), or one factory per environment.
        observation_space: Space of one agent's observation.
        action_space: Space of one agent's action (Discrete).
        agent_ids: The learning agents in the env; each gets its own network.
        config: Hyperparameters (default preset if None).
        total_steps: Env steps to take, all environments counted (the last
            segments may overshoot by less than ``n_steps`` per thread).
        num_envs: Environments, one learner thread each (default: 2, or one per
            factory in ``env_fn``).
        seed: Seeds network init (agent k: ``seed + k``), the resets (env i,
            episode k: ``seed + i + k * N``) and thread i's sampling.
        callback: Called in this thread after each segment report with a
            :class:`TrainProgress`; return True to stop early.
        start_method: ``"spawn"`` or ``"forkserver"`` for the env worker processes.
        agents: Agents to continue training (e.g. loaded from checkpoints to resume);
            default: fresh agents built from ``config`` and ``seed``.
        processes: Env worker processes (default: when N > 1) or in process.

    Returns:
        Agent id -> trained :class:`A3C` agent, ready to act or save.

    Raises:
        WorkerError: If an environment raised (:class:`~agents.vector.VectorEnvError`,
            with the worker's traceback) or its worker died.
        KeyboardInterrupt: On Ctrl-C/SIGTERM; threads and env workers are stopped first.
    """
    config = config if config is not None else A3CConfig()
    if total_steps < 1:
        raise ValueError(f"need total_steps >= 1, got {total_steps}")
    agents = agents_for(A3C, observation_space, action_space, agent_ids, config, seed, agents)
    run = ThreadRun(agents, config.n_steps, config.reward_scale, total_steps, seed, _segment_learner(config))
    return run_threads(run, vector_env(env_fn, num_envs, start_method, processes), callback, "a3c-learner")
