"""The common agent interface and the shared config plumbing.

Every algorithm (PPO, DQN, DDPG, TD3, A3C, IMPALA) is an :class:`Agent`, so one
loop (:func:`agents.loop.run_loop`) can drive any mix of them over N environments
(``agents/vector.py``). The batch pair is what an algorithm implements:

1. ``act_batch(obs, columns)`` picks the actions for a batch of observations in
   one forward pass, row j from environment ``columns[j]``, and keeps what
   learning needs (log prob, value) per environment;
2. ``observe_batch(obs, actions, rewards, next_obs, terminated, truncated,
   columns)`` records the transitions that followed, one per row;
3. ``update()`` is called once per vector step; the agent does every learning
   step that the transitions observed since the last call are due (a full
   rollout, every ``train_freq`` steps, ...; so an update-to-data ratio such as
   DQN's ``gradient_steps / train_freq`` per transition holds for any N) and
   returns namespaced metrics (``losses/...``, ``charts/...``), else ``{}``.

An algorithm whose ``act_batch`` is a forward pass followed by picking actions also names
the pass (``acting_chain``) and the picking (``act_from``), so that the loop can run the pass
for several ACs at once (agents/batched.py) and leave each AC its own picking.

``act(obs)`` and ``observe(...)`` for ONE observation are derived from the batch
pair here, once: ``act`` is a batch of one outside any environment (it keeps
nothing for ``observe``, so acting between training steps, as a validation
does, leaves training alone), ``observe`` a batch of one in environment 0.

Hyperparameters live in one frozen :class:`AgentConfig` dataclass per
algorithm, with named presets (``"default"``, ``"paper"``), in ``agents/configs.py``
(no torch there; re-exported here and by each algorithm's module). Checkpoints are
self-describing (``agents/checkpoint.py``).
"""

from __future__ import annotations

import abc
import contextlib
import logging
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import gymnasium
import numpy as np
import torch

from agents import observations
from agents.buffers import ReplayBuffer
from agents.configs import AgentConfig, check_range
from agents.errors import AgentError
from agents.networks import obs_to_tensor
from agents.observations import image_space, is_nav_space

__all__ = ["Agent", "AgentConfig", "ObservationError", "check_frames", "check_observation_space",
           "check_observations", "check_range", "check_variant", "due", "resolve_device", "seeded_init"]

logger = logging.getLogger(__name__)


def resolve_device(name: str = "auto") -> str:
    """``"auto"`` -> ``"cuda"`` when a CUDA device is available, else ``"cpu"``; others are checked.

    Raises:
        ValueError: For an unknown device name, or ``"cuda"`` without a CUDA device.
    """
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"unknown device {name!r}; use auto, cpu or cuda") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} asked for, but torch sees no CUDA device; use --device cpu or auto")
    return name


def due(before: int, now: int, every: int, start: int = 0) -> int:
    """How many multiples ``m`` of ``every`` with ``m >= start`` lie in ``(before, now]``.

    The steps counter of an off-policy agent moves by one per transition in one
    environment and by up to N per ``update()`` call with N environments; this is
    how many training phases (or target copies) fell due in between, so the
    update-to-data ratio does not depend on N. For ``now = before + 1`` it is 1
    exactly when ``now >= start`` and ``now % every == 0``.
    """
    low = max(before, start - 1)
    return max(0, now // every - low // every) if now >= start else 0


class ObservationError(AgentError, ValueError):
    """An agent is given observations of another variant or frame stack than it was trained
    on; the message names both and the option that fixes it."""


def check_observation_space(algo: str, observation_space) -> None:
    """Refuse an observation space the networks cannot take: a Box or ``Dict(image,
    measurements)`` only (agents/networks.py make_encoder)."""
    if isinstance(observation_space, gymnasium.spaces.Box) or is_nav_space(observation_space):
        return
    raise ValueError(f"{algo.upper()} needs a Box observation space or Dict(image, measurements), got "
                     f"{observation_space!r}; flatten other Dict/Tuple observations with a gymnasium wrapper")


def _shape(shape) -> str:
    return "x".join(map(str, shape))


def _dims(space_or_array) -> str:
    """The shape of a Box or an array as ``84x84x12``."""
    shape = space_or_array.shape if hasattr(space_or_array, "shape") else np.shape(space_or_array)
    return _shape(shape)


def observation_variant(space_or_obs) -> str:
    """Which of cosim's ``--obs`` variants an observation space (or one observation) is: "nav"
    for ``Dict(image, measurements)``, "image" for an (H, W, C) image, "state" for a flat
    vector (the state track, cosim.state; any vector observation reads so)."""
    if is_nav_space(space_or_obs) or isinstance(space_or_obs, Mapping):
        return "nav"
    shape = space_or_obs.shape if hasattr(space_or_obs, "shape") else np.shape(space_or_obs)
    return "image" if len(shape) == 3 else "state"


def describe_observation(space_or_obs) -> str:
    """The variant of an observation space (or of one observation) in words, as the refusals
    name it: ``nav observations (84x84x12 image + 7 measurements)``, ``image observations
    (84x84x12)`` or ``state observations (65)``."""
    variant = observation_variant(space_or_obs)
    if variant == "nav":
        return (f"nav observations ({_dims(space_or_obs['image'])} image + "
                f"{_dims(space_or_obs['measurements'])} measurements)")
    return f"{variant} observations ({_dims(space_or_obs)})"


def check_variant(trained: gymnasium.Space, given, what: str) -> None:
    """Refuse observations (a space or one observation) of another variant than ``trained``:
    the camera image alone, with the nav measurements, or a state vector (cosim's ``--obs
    image|nav|state``, :func:`observation_variant`), in one line naming both and the fix (every
    checkpoint records its space, Box or Dict).

    Raises:
        ObservationError: the variants differ.
    """
    variant = observation_variant(trained)
    if variant == observation_variant(given):
        return
    raise ObservationError(
        f"{what} was trained on {describe_observation(trained)} but is given "
        f"{describe_observation(given)}; use --obs {variant} (the run's obs) with it")


def check_frames(trained: gymnasium.Space, given_shape: tuple, what: str) -> None:
    """Refuse observations with another number of stacked camera frames than ``trained``, in
    one line naming both and the fix (the frame stack is recorded in every checkpoint as its
    observation shape, H x W x 3K; docs/task.md, "Observation"). ``trained`` may be a nav
    space: its image is compared.

    Raises:
        ObservationError: the image sizes match but the frame counts differ.
    """
    shape = tuple(getattr(image_space(trained), "shape", None) or ())
    given_shape = tuple(given_shape)
    if len(shape) != 3 or len(given_shape) != 3 or shape == given_shape or shape[:2] != given_shape[:2]:
        return
    k, k_given = shape[-1] / 3, given_shape[-1] / 3
    fmt = lambda v: f"{v:g}"  # noqa: E731 - whole frames print as integers
    raise ObservationError(
        f"{what} was trained on {fmt(k)} stacked camera frame(s) ({_shape(shape)}) but "
        f"is given {fmt(k_given)} ({_shape(given_shape)}); use --frame-stack {fmt(k)} "
        f"(the run's frame_stack) with it")


def check_observations(trained: gymnasium.Space, given: gymnasium.Space, what: str) -> None:
    """:func:`check_variant`, then :func:`check_frames` on the images: an agent trained on
    ``trained`` refuses ``given`` in one line unless they are the same variant and stack."""
    check_variant(trained, given, what)
    check_frames(trained, image_space(given).shape, what)


@contextlib.contextmanager
def seeded_init(seed: int):
    """Run network construction under ``seed`` without touching the caller's torch RNG.

    Several agents in one process each build their networks deterministically from
    their own seed, and the global torch RNG stream is left as it was.
    """
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


class Agent(abc.ABC):
    """A learning agent: acts on a batch of observations, learns from what it observes.

    Subclasses set ``algo`` and ``config_class`` and implement ``check_spaces``, ``_build``,
    ``act_batch``, ``observe_batch`` and ``update`` (the single-row ``act``/``observe`` are
    derived here). The default ``state_dict`` saves every
    module in ``self.networks``, every optimizer in ``self.optimizers`` and the
    dict returned by ``_extra_state`` (counters, schedules); override all three
    only when that is not enough.

    Attributes:
        algo: Registry name (``"ppo"``, ``"dqn"``, ...).
        config: The algorithm's frozen config dataclass.
        observation_space: Gymnasium space of one observation.
        action_space: Gymnasium space of one action.
        device: Torch device the networks live on.
        networks: Name -> ``nn.Module`` (everything with weights).
        optimizers: Name -> ``torch.optim.Optimizer``.
    """

    algo: ClassVar[str]
    config_class: ClassVar[type[AgentConfig]]
    policy_only: bool = False
    """True when loaded from a policy checkpoint: it acts, but holds no optimizer or target state."""
    optimizer_learning_rates: ClassVar[dict[str, str]] = {}
    """Optimizer name (``self.optimizers``) -> the config field holding its learning rate, so
    that a changed config reaches the optimizers (:func:`agents.checkpoint.retune_checkpoint`)."""

    def __init__(
        self,
        observation_space: gymnasium.Space,
        action_space: gymnasium.Space,
        config: AgentConfig | None = None,
        seed: int = 0,
        device: str = "cpu",
    ):
        config = self.config_class() if config is None else config
        if not isinstance(config, self.config_class):
            raise TypeError(
                f"{type(self).__name__} needs a {self.config_class.__name__}, got {type(config).__name__}"
            )
        self.check_spaces(observation_space, action_space)
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not 0 <= seed < 2**64:
            raise ValueError(f"{type(self).__name__}(seed=...): the seed must be a whole number "
                             f"0..2**64-1 (numpy's and torch's generators), got {seed!r}")
        self.config = config
        self.observation_space = observation_space
        self.action_space = action_space
        self.seed = int(seed)
        self.device = torch.device(device)
        self.rng = np.random.default_rng(seed)
        # Per-agent generator: sampling does not depend on what other agents drew.
        self.generator = torch.Generator(device=self.device).manual_seed(seed)
        self.networks: dict[str, torch.nn.Module] = {}
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        with seeded_init(seed):
            self._build()

    # ---- what every algorithm implements -------------------------------------------
    @classmethod
    @abc.abstractmethod
    def check_spaces(cls, observation_space: gymnasium.Space, action_space: gymnasium.Space) -> None:
        """Raise ``ValueError`` naming the space and the fix if the algorithm cannot handle it."""

    @abc.abstractmethod
    def _build(self) -> None:
        """Create networks and optimizers (runs under the agent's seed)."""

    @torch.no_grad()
    def act_batch(self, obs, columns: np.ndarray | None, deterministic: bool = False) -> np.ndarray:
        """Actions for a batch of observations in one forward pass; row j comes from environment
        ``columns[j]``, and what learning needs of it is kept for that environment's next
        :meth:`observe_batch`. ``columns=None``: acting outside training, nothing is kept.

        The default runs :meth:`acting_chain`'s modules on the observation tensor and hands
        their output to :meth:`act_from` (the grouped path of agents/batched.py, for one AC);
        an algorithm without a chain for some step (TD3's random phase) overrides it.

        Returns:
            An int64 array of shape (B,) for Discrete spaces, float32 (B, *shape) for Box spaces.
        """
        chain = self.acting_chain(deterministic)
        if chain is None:
            raise NotImplementedError(f"{type(self).__name__} has neither act_batch nor an acting chain")
        outputs = obs_to_tensor(obs, self.device)
        for module in chain:
            outputs = module(outputs)
        return self.act_from(outputs, columns, deterministic)

    @abc.abstractmethod
    def observe_batch(self, obs, actions, rewards, next_obs, terminated, truncated, columns) -> None:
        """Record the transitions that followed :meth:`act_batch`, one per row (environment
        ``columns[j]``); ``next_obs`` of a finished episode is its true final observation."""

    @abc.abstractmethod
    def update(self) -> dict[str, float]:
        """Learn what is due; return namespaced metrics, or ``{}`` if nothing was learned."""

    # ---- acting in a group with other ACs (agents/batched.py) -----------------------
    def acting_chain(self, deterministic: bool = False) -> tuple[torch.nn.Module, ...] | None:
        """The modules that :meth:`act_batch`'s forward pass applies in turn to the observation
        tensor, when :meth:`act_from` picks the actions from their output; None (the default)
        when this step's actions need no such pass (TD3's random phase) or the algorithm has
        none: the AC then acts on its own, with :meth:`act_batch`."""
        return None

    def act_from(self, outputs, columns: np.ndarray | None, deterministic: bool = False) -> np.ndarray:
        """:meth:`act_batch` after its forward pass: the actions (and what learning keeps of
        them) from ``outputs``, the :meth:`acting_chain`'s output for this batch, drawing from
        the agent's generators exactly as :meth:`act_batch` does."""
        raise NotImplementedError(f"{type(self).__name__} has no acting chain")

    def prepare_envs(self, num_envs: int) -> None:  # noqa: B027 - optional hook
        """Called once before a loop steps ``num_envs`` environments (e.g. replay rings)."""

    progress_remaining: float = 1.0
    """Fraction of the loop's budget of environment steps still to take when ``update()`` runs
    (1 -> 0), set by :func:`agents.loop.run_loop` before each call (SB3's
    ``_current_progress_remaining``): what a learning-rate anneal reads (A3C, IMPALA)."""

    # ---- the single-row pair, derived from the batch pair ---------------------------
    def act(self, obs, deterministic: bool = False):
        """The action for ONE observation (checked against the agent's space): a batch of one
        outside any environment, so nothing is kept for :meth:`observe`.

        Returns:
            An ``int`` for Discrete spaces, a float32 array for Box spaces.
        """
        action = np.asarray(self.act_batch(self.one_row(obs), None, deterministic=deterministic))[0]
        return int(action) if isinstance(self.action_space, gymnasium.spaces.Discrete) else action

    def observe(self, obs, action, reward: float, next_obs, terminated: bool, truncated: bool) -> None:
        """Record one transition of environment 0 (a batch of one for :meth:`observe_batch`)."""
        self.observe_batch(self.one_row(obs), np.asarray([action]), np.asarray([reward], np.float32),
                           self.one_row(next_obs), np.asarray([terminated]), np.asarray([truncated]),
                           np.zeros(1, np.int64))

    def observe_demonstration(self, obs, action, reward: float, next_obs, terminated: bool, truncated: bool,
                              column: int = 0) -> None:
        """Store one demonstrated transition of environment ``column`` (a scripted driver's; the
        reward as the env gave it) in the replay, marked as a demonstration (DQfD, Hester et
        al. 2018). Unlike :meth:`observe` it does not count in the agent's steps, so the
        exploration schedule and the learning start stay the run's. Replay learners only.

        Raises:
            ValueError: the agent has no replay buffer (an on-policy learner).
        """
        buffer = getattr(self, "buffer", None)
        if not isinstance(buffer, ReplayBuffer):
            raise ValueError(f"{self.algo} learns on-policy and keeps no replay for demonstrations; "
                             f"use dqn, ddpg or td3")
        buffer.add(obs, action, float(reward) * self.config.reward_scale, next_obs, bool(terminated),
                   bool(truncated), column=column, demo=True)

    def _extra_state(self) -> dict[str, Any]:
        """Plain values (ints, floats, tensors) besides weights needed to resume."""
        return {}

    def _load_extra_state(self, state: Mapping[str, Any]) -> None:  # noqa: B027 - optional hook
        """Restore what ``_extra_state`` returned (nothing by default)."""

    # ---- shared plumbing ------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Weights, optimizer states and counters; only tensors and plain Python values."""
        return {
            "networks": {k: v.state_dict() for k, v in self.networks.items()},
            "optimizers": {k: v.state_dict() for k, v in self.optimizers.items()},
            "extra": self._extra_state(),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned.

        Raises:
            KeyError: If a network or optimizer is missing from ``state``.
        """
        missing = sorted(set(self.networks) - set(state["networks"]))
        if missing:
            raise KeyError(f"state has no weights for network(s) {missing}")
        for name, net in self.networks.items():
            net.load_state_dict(state["networks"][name])
        for name, optimizer in self.optimizers.items():
            if name in state.get("optimizers", {}):
                optimizer.load_state_dict(state["optimizers"][name])
        self._load_extra_state(state.get("extra", {}))

    def save(self, path, policy_only: bool = False, policy_dtype: str = "float32") -> None:
        """Write a self-describing checkpoint (see :func:`agents.checkpoint.save_checkpoint`);
        ``policy_only`` keeps only what acting needs, its float weights as ``policy_dtype``."""
        from agents.checkpoint import save_checkpoint

        save_checkpoint(path, self, policy_only=policy_only, policy_dtype=policy_dtype)

    @classmethod
    def load(cls, path, device: str = "cpu") -> Agent:
        """Load a checkpoint of this algorithm; raise ``CheckpointError`` for another one."""
        from agents.checkpoint import load_checkpoint

        return load_checkpoint(path, device=device, expected_algo=cls.algo)

    @classmethod
    def from_spaces(
        cls,
        observation_space: gymnasium.Space,
        action_space: gymnasium.Space,
        config: AgentConfig | None = None,
        seed: int = 0,
        device: str = "cpu",
    ) -> Agent:
        """Build an untrained agent for these spaces (the constructor, by name)."""
        return cls(observation_space, action_space, config=config, seed=seed, device=device)

    def one_row(self, obs):
        """One observation -> a batch of one (numpy), checking its variant and shape (an image
        array, or a dict of image and measurements for a nav space).

        Raises:
            ObservationError: another variant or frame stack than the agent was built for.
            ValueError: another shape (e.g. a batch where one observation is expected).
        """
        check_variant(self.observation_space, obs, f"{self.algo} agent")
        obs = observations.asarray(obs)
        for key, space in observations.parts(self.observation_space).items():
            array = obs[key] if key else obs
            if array.shape != space.shape:
                if array.ndim == 3 and array.shape[:2] == space.shape[:2]:
                    check_frames(space, array.shape, f"{self.algo} agent")
                raise ValueError(
                    f"{self.algo} agent expected {f'{key} ' if key else 'an observation '}of shape "
                    f"{space.shape}, got {array.shape}; pass one observation at a time"
                )
        return observations.take(obs, np.newaxis)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(obs={self.observation_space}, act={self.action_space}, "
            f"seed={self.seed}, device={self.device})"
        )


class ReplayAgent(Agent):
    """An off-policy learner on a :class:`~agents.buffers.ReplayBuffer` (DQN, DDPG, TD3).

    Subclasses keep ``self.buffer``, count ``self.steps`` and ``self.gradient_updates``, and
    implement ``_gradient_step`` (one minibatch update, returning its metrics); pre-training on
    demonstrations and the counters' checkpointing are shared here.
    """

    steps: int
    gradient_updates: int
    _updated_to: int

    @abc.abstractmethod
    def _gradient_step(self) -> dict[str, float]:
        """One gradient step on a minibatch of the replay; returns its metrics."""

    def _after_pretrain(self) -> None:  # noqa: B027 - optional hook
        """Called once after :meth:`pretrain`'s updates (DQN copies its target network)."""

    def pretrain(self, updates: int, on_update: Callable[[], None] | None = None) -> dict[str, float]:
        """``updates`` gradient steps on what the replay holds (its demonstrations, before any
        env step: DQfD's pre-training phase), ``on_update()`` after each (a progress bar), then
        :meth:`_after_pretrain`; the agent's steps, and so its exploration schedule, learning
        start and random warm-up, stay where they were.

        Raises:
            ValueError: the replay is empty.
        """
        if not len(self.buffer):
            raise ValueError(f"{self.algo.upper()} pretrain: the replay is empty; observe demonstrations first")
        metrics: dict[str, float] = {}
        for _ in range(int(updates)):
            metrics.update(self._gradient_step())
            if on_update is not None:
                on_update()
        self._after_pretrain()
        return metrics

    def _extra_state(self) -> dict[str, Any]:
        return {"steps": self.steps, "gradient_updates": self.gradient_updates}

    def _load_extra_state(self, state: Mapping[str, Any]) -> None:
        self.steps = self._updated_to = int(state.get("steps", 0))
        self.gradient_updates = int(state.get("gradient_updates", 0))
