"""A3C: asynchronous advantage actor-critic (Mnih et al. 2016, arXiv:1602.01783).

One algorithm on the one loop (:func:`agents.loop.run_loop`), its hooks the
batch pair and ``update``: every ``n_steps`` transitions of an environment
(a segment) the agent computes the gradients of the loss and applies them to
the *shared* network with a *shared* Adam (:meth:`SharedAdam.apply_gradients`).

* **Asynchronous** (:func:`train_a3c`, ``cosim train --algo a3c``), the real
  thing: the loop runs one actor-learner thread per environment of ONE vector
  env (``agents/vector.py``; thread k owns env index k), each with its
  :meth:`A3C.worker` per agent: a private copy of the network that acts,
  computes its segment's gradients and applies them to the shared network,
  lock-free ("Hogwild", Recht et al. 2011), then reads the shared weights. One
  shared model per agent id: the driving benchmark trains N cars, each with its
  own network, all A3C.
* **In process** (the loop without ``actors``): the agent is its own worker,
  n-step advantage actor-critic on its own transitions. A trained policy acts
  in the test protocol through the derived ``act``.

Loss per rollout (means over the T steps; RLlib 0.8, which the paper used,
sums, so the paper's lr is not directly comparable):
``pg_loss = -mean(A_t log pi(a_t|s_t))``, ``v_loss = 0.5 mean((R_t - V(s_t))^2)``,
``loss = pg_loss + vf_coef v_loss - ent_coef H[pi]``, with ``A_t, R_t`` from GAE
(lambda 1.0 = the n-step returns of the A3C paper), and the global gradient
norm clipped before the shared step.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar

import gymnasium
import numpy as np
import torch
from torch import nn

from agents import observations
from agents.async_env import vector_env
from agents.base import Agent, check_observation_space
from agents.configs import A3CConfig, AgentConfig
from agents.loop import Progress, run_loop
from agents.networks import ActorCritic, obs_to_tensor
from agents.returns import gae
from agents.workers import Rollout, RolloutBuilder, agents_for, private_copy, worker_seed

__all__ = ["A3C", "A3CConfig", "SharedAdam", "a3c_loss", "actor_learners", "train_a3c"]

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- shared optimizer


class SharedAdam(torch.optim.Adam):
    """Adam whose moment estimates are shared by A3C's learner threads.

    The state is created eagerly (plain Adam creates it on the first step) and
    :meth:`apply_gradients` steps it with gradients computed elsewhere (a
    thread's local copy of the network), so no thread ever writes another's
    ``.grad``: Hogwild (Recht et al. 2011), lock-free, as ikostrikov/pytorch-a3c
    does across processes. ``step()`` is plain Adam, with the same arithmetic.
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
    """A3C agent: n-step advantage actor-critic whose gradients go to a shared model.

    In process (the loop's hooks on this agent) the shared model is its own: one update
    per ``n_steps`` transitions of an environment. :meth:`worker` gives one of
    :func:`train_a3c`'s actor-learners: a copy that acts and computes gradients with a
    private copy of the network and applies them to this agent's model with the shared
    Adam, lock-free (:meth:`SharedAdam.apply_gradients`), then reads the shared weights.

    Attributes:
        model: The ``ActorCritic`` network this agent acts with (a worker's private copy).
        optimizer: The :class:`SharedAdam` of the shared model.
        num_updates: Updates applied to the shared model (a worker counts on the shared agent).
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
        self._builders: dict[int, RolloutBuilder] = {}  # env -> its segment so far
        self._shared: A3C = self  # the agent whose model the gradients go to
        self._lock: threading.Lock | None = None  # guards the shared update counter (workers)
        self._seen = 0  # the shared update count when this agent's weights were read
        self.num_updates = 0

    def worker(self, generator: torch.Generator, lock: threading.Lock) -> A3C:
        """An actor-learner of this agent: a private copy of the network, sampling with
        ``generator``; its updates go to this agent's model, counted under ``lock``."""
        worker = copy.copy(self)
        worker.model, worker.generator, worker._builders = private_copy(self.model), generator, {}
        worker._shared, worker._lock = self, lock
        with lock:
            worker._seen = self.num_updates
        return worker

    def acting_chain(self, deterministic: bool = False) -> tuple[nn.Module, ...]:
        return (self.model,)

    @torch.no_grad()
    def act_from(self, outputs, columns: np.ndarray | None, deterministic: bool = False) -> np.ndarray:
        logits, _ = outputs
        if deterministic:
            return logits.argmax(-1).cpu().numpy()
        # Sampled on the model's device with the agent's own generator (same device).
        probs = torch.log_softmax(logits, dim=-1).exp()
        return torch.multinomial(probs, 1, generator=self.generator)[:, 0].cpu().numpy()

    def observe_batch(self, obs, actions, rewards, next_obs, terminated, truncated, columns) -> None:
        rewards = np.asarray(rewards, np.float32) * self.config.reward_scale
        for j, column in enumerate(np.asarray(columns).tolist()):
            builder = self._builders.setdefault(column, RolloutBuilder("self"))
            builder.add(observations.take(obs, j), actions[j], rewards[j], observations.take(next_obs, j),
                        terminated[j], truncated[j])

    def update(self) -> dict[str, float]:
        """One shared update per environment whose segment holds ``n_steps`` transitions."""
        metrics: dict[str, float] = {}
        for column in sorted(self._builders):
            if len(self._builders[column]) >= self.config.n_steps:
                metrics = self._learn(self._builders[column].build())
        return metrics

    def _learn(self, rollout: Rollout) -> dict[str, float]:
        config, shared = self.config, self._shared
        lr = config.learning_rate * (self.progress_remaining if config.anneal_lr else 1.0)
        metrics = compute_gradients(self.model, rollout, config)
        shared.optimizer.apply_gradients([p.grad for p in self.model.parameters()], lr)
        with self._lock or contextlib.nullcontext():
            shared.num_updates += 1
            # shared updates other workers applied since this one's weights were read
            staleness = shared.num_updates - 1 - self._seen
            self._seen = shared.num_updates
        if shared is not self:
            self.model.load_state_dict(shared.model.state_dict())
            metrics["charts/staleness"] = float(staleness)
        metrics["charts/learning_rate"] = lr
        metrics["charts/num_updates"] = float(shared.num_updates)
        return metrics

    def _extra_state(self) -> dict[str, Any]:
        return {"num_updates": self.num_updates}

    def _load_extra_state(self, state) -> None:
        self.num_updates = int(state.get("num_updates", 0))


def actor_learners(agents: Mapping[str, A3C], seed: int) -> Callable[[int], dict[str, A3C]]:
    """The actor-learners of environment k (one :meth:`A3C.worker` per agent), what
    :func:`agents.loop.run_loop` runs one thread of per environment (``actors=``); thread
    k samples with one generator seeded ``worker_seed(seed, k)``."""
    lock = threading.Lock()

    def actors(k: int) -> dict[str, A3C]:
        generator = torch.Generator().manual_seed(worker_seed(seed, k))
        return {aid: agent.worker(generator, lock) for aid, agent in agents.items()}

    return actors


# ----------------------------------------------------------------------------- asynchronous training


def train_a3c(
    env_fn: Callable[[], Any] | Sequence[Callable[[], Any]],
    observation_space: gymnasium.Space,
    action_space: gymnasium.Space,
    agent_ids: Sequence[str] = ("agent_0",),
    config: A3CConfig | None = None,
    total_steps: int = 100_000,
    num_envs: int | None = None,
    seed: int = 0,
    callback: Callable[[Progress], bool | None] | None = None,
    start_method: str = "spawn",
    agents: dict[str, A3C] | None = None,
    processes: bool | None = None,
) -> dict[str, A3C]:
    """Train one A3C agent per agent id: one actor-learner thread per environment of one vector env.

    :func:`agents.loop.run_loop` with ``actors=``:func:`actor_learners`: thread k steps env
    k of the vector env (``agents/vector.py``; the env steps in its worker process, or in
    process for N = 1) through the loop's schedule with its workers (:meth:`A3C.worker`),
    which apply their gradients to the shared network with the shared Adam, lock-free,
    whenever a segment of ``n_steps`` transitions is in: asynchronous, as in the paper. Torch
    releases the GIL inside its ops and a thread waiting for its env holds no lock, so the
    threads overlap. Runs are not reproducible step for step for N > 1 (the order of the
    threads' updates varies); with N = 1 they are.

    Args:
        env_fn: Picklable zero-argument factory (a ParallelEnv, or a Gymnasium env
            for one agent), or one factory per environment.
        observation_space: Space of one agent's observation.
        action_space: Space of one agent's action (Discrete).
        agent_ids: The learning agents in the env; each gets its own network.
        config: Hyperparameters (default preset if None).
        total_steps: Env steps to take, all environments counted.
        num_envs: Environments, one learner thread each (default: 2, or one per
            factory in ``env_fn``).
        seed: Seeds network init (agent k: ``seed + k``), the resets (env i,
            episode k: ``seed + i + k * N``) and thread i's sampling.
        callback: Called in this thread after each env step a thread took and learnt
            from, with the loop's :class:`~agents.loop.Progress`; return True to stop early.
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
    venv = vector_env(env_fn, num_envs, start_method, processes)
    try:
        run_loop(agents, venv, total_steps, callback, seed=seed, actors=actor_learners(agents, seed))
    finally:
        venv.close()
    return agents
