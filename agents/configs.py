"""The six algorithms' hyperparameters: one frozen dataclass per algorithm, with no torch.

:class:`AgentConfig` is the base (``preset``, ``from_dict``, ``replace``, ``to_dict``);
:class:`PPOConfig`, :class:`DQNConfig`, :class:`TD3Config`, :class:`DDPGConfig`,
:class:`A3CConfig` and :class:`IMPALAConfig` are each algorithm's fields, validated in
``__post_init__``, with the named presets (``"default"``, ``"paper"``) in ``PRESETS``.

They live here, apart from the algorithms (``agents/ppo.py`` ...), so that the layers above
(the presets, the command line, a training run's config, PBT, Ray trials and the environment
worker processes that unpickle a run's config) hold the typed config without importing
torch. The algorithm modules import their class from here and re-export it
(``from agents.ppo import PPOConfig`` keeps working), and each agent class names its config
class as ``config_class``; the catalogue (``agents/registry.py``, ``get_config_class``)
finds it by algorithm name without importing the algorithm. Checkpoints store a config as
``to_dict()`` and rebuild it with ``from_dict`` (docs/design.md, "One hyperparameter from
the command line to the optimiser").
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Mapping
from typing import Any, ClassVar

__all__ = ["A3CConfig", "AgentConfig", "DDPGConfig", "DQNConfig", "IMPALAConfig", "PPOConfig", "TD3Config",
           "check_range"]


def check_range(
    name: str,
    value: float,
    low: float | None = None,
    high: float | None = None,
    *,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
) -> None:
    """Raise ``ValueError`` naming ``name`` and the valid range if ``value`` is outside it."""
    bad = value != value  # NaN
    if low is not None:
        bad |= value < low if low_inclusive else value <= low
    if high is not None:
        bad |= value > high if high_inclusive else value >= high
    if bad:
        left = "-inf" if low is None else f"{'[' if low_inclusive else '('}{low}"
        right = "inf" if high is None else f"{high}{']' if high_inclusive else ')'}"
        raise ValueError(f"{name}={value!r} is out of range; valid range is {left}, {right}")


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """Base class of the per-algorithm hyperparameter dataclasses.

    Subclasses declare fields (each with a one-line docstring under it), validate
    them in ``__post_init__`` and list named presets in ``PRESETS`` as
    ``{name: {field: value}}`` overrides of the field defaults.
    """

    PRESETS: ClassVar[Mapping[str, Mapping[str, Any]]] = {"default": {}}

    reward_scale: float = 1.0
    """Every reward is multiplied by this before the agent learns from it (returns
    in the thousands make value targets, and so the shared encoder's gradients, huge)."""
    action_repeat: int = 1
    """Environment steps each chosen action is held for: the agent decides every
    ``action_repeat``-th step and learns from the sum of the rewards in between (frame
    skipping, Mnih et al. 2015's k = 4). A property of the policy, so its checkpoint carries it
    and every test drives it at that rate (cosim.wrappers.ActionRepeat in training,
    eval/testing/rollout.py ``RepeatPolicy`` in the test). 1: an action every step."""
    batched_acting: bool = True
    """Act in one grouped forward pass with the loop's other ACs of this algorithm and
    architecture (agents/batched.py: their weights stacked, re-copied when they change), bit
    for bit what each AC's own pass gives; False: one forward pass per AC, the path before
    issue 59 (for comparison; it learns the same)."""

    def __post_init__(self):
        check_range("reward_scale", self.reward_scale, 0, low_inclusive=False)
        check_range("action_repeat", self.action_repeat, 1)
        if int(self.action_repeat) != self.action_repeat:
            raise ValueError(f"action_repeat={self.action_repeat!r} must be a whole number of steps")
        hidden = getattr(self, "hidden", None)  # every algorithm's MLP sizes (issue 57 item 12)
        if hidden is not None and (not isinstance(hidden, tuple | list) or not hidden or any(
                isinstance(h, bool) or not isinstance(h, numbers.Integral) or h < 1 for h in hidden)):
            raise ValueError(f"hidden={hidden!r} must be a non-empty list of layer sizes >= 1, "
                             "e.g. [64, 64]")

    @classmethod
    def preset(cls, name: str = "default", **overrides: Any) -> AgentConfig:
        """Build the named preset, optionally with some fields changed.

        Args:
            name: A key of ``PRESETS`` (``"default"``, ``"paper"``, ...).
            **overrides: Field values that replace the preset's.

        Raises:
            ValueError: For an unknown preset or field name (the message lists the valid ones).
        """
        if name not in cls.PRESETS:
            raise ValueError(f"unknown {cls.__name__} preset {name!r}; valid presets: {sorted(cls.PRESETS)}")
        return cls.from_dict({**cls.PRESETS[name], **overrides})

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> AgentConfig:
        """Build a config from a plain dict (YAML, a checkpoint, config.yaml), rejecting unknown keys."""
        return cls(**cls._checked(values))

    def replace(self, **changes: Any) -> AgentConfig:
        """Return a copy with some fields changed (``dataclasses.replace``: validated again by
        ``__post_init__``; an unknown field is refused listing the valid ones)."""
        return dataclasses.replace(self, **self._checked(changes))

    @classmethod
    def _checked(cls, values: Mapping[str, Any]) -> dict[str, Any]:
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(fields))
        if unknown:
            raise ValueError(f"unknown {cls.__name__} field(s) {unknown}; valid fields: {sorted(fields)}")
        # YAML and some serialisers turn tuples into lists; tuple fields take them back.
        return {k: tuple(v) if isinstance(v, list) and "tuple" in str(fields[k].type) else v
                for k, v in values.items()}

    def to_dict(self) -> dict[str, Any]:
        """Plain-dict view (``dataclasses.asdict``) for logs and checkpoints."""
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class PPOConfig(AgentConfig):
    """PPO hyperparameters. ``preset("paper")`` gives SPEC section 5 (the paper's Table 3)."""

    learning_rate: float = 3e-4
    """Adam learning rate."""
    rollout_steps: int = 2048
    """transitions collected per training iteration (per agent, summed over environments)."""
    batch_size: int = 128
    """SGD minibatch size."""
    epochs: int = 10
    """passes over each rollout."""
    gamma: float = 0.99
    """discount factor."""
    gae_lambda: float = 0.95
    """GAE lambda (bias/variance trade-off of the advantages)."""
    clip_coef: float = 0.2
    """surrogate clipping range epsilon."""
    kl_coef: float = 0.2
    """initial coefficient of the KL penalty (0 disables it)."""
    kl_target: float = 0.01
    """KL divergence the adaptive coefficient aims for."""
    vf_coef: float = 0.5
    """value-loss coefficient."""
    ent_coef: float = 0.0
    """entropy-bonus coefficient."""
    max_grad_norm: float = 0.5
    """global gradient-norm clip."""
    norm_adv: bool = True
    """normalise advantages per minibatch."""
    value_norm: str = "none"
    """value targets normalised by the running mean and standard deviation of the returns (the
    value head predicts ``(R - mean) / std``, denormalised wherever a value is used: GAE,
    bootstraps; MAPPO's ValueNorm, Yu et al. 2022): "all"; "shared": only when the policy and
    the value share one encoder (images: the Nature CNN, whose gradient the value loss otherwise
    swamps, docs/agents.md); "none": raw returns, the update before issue 59."""
    shared_value_grad: float = 1.0
    """scale of the value loss's gradient into an encoder the value shares with the policy
    (images: the Nature CNN); the value head learns from the whole loss either way, separate
    encoders (vectors) ignore it. 1: the update before issue 59; docs/agents.md."""
    hidden: tuple[int, ...] = (64, 64)
    """MLP hidden sizes for vector observations (images use the Nature CNN)."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "default": {},
        # SPEC section 5, Table 3. Unlisted fields keep the defaults above.
        "paper": {
            "learning_rate": 1e-3, "epochs": 8, "vf_coef": 1.0, "ent_coef": 0.01, "clip_coef": 0.3,
            "kl_coef": 0.3, "kl_target": 0.03, "gae_lambda": 0.99,
        },
    }

    def __post_init__(self):
        super().__post_init__()
        check_range("learning_rate", self.learning_rate, 0, 1, low_inclusive=False)
        check_range("rollout_steps", self.rollout_steps, 1)
        check_range("batch_size", self.batch_size, 1, self.rollout_steps)
        check_range("epochs", self.epochs, 1)
        check_range("gamma", self.gamma, 0, 1)
        check_range("gae_lambda", self.gae_lambda, 0, 1)
        check_range("clip_coef", self.clip_coef, 0, None, low_inclusive=False)
        check_range("kl_coef", self.kl_coef, 0)
        check_range("kl_target", self.kl_target, 0, None, low_inclusive=False)
        check_range("vf_coef", self.vf_coef, 0)
        check_range("ent_coef", self.ent_coef, 0)
        check_range("max_grad_norm", self.max_grad_norm, 0, None, low_inclusive=False)
        check_range("shared_value_grad", self.shared_value_grad, 0, 1)
        if self.value_norm not in VALUE_NORMS:
            raise ValueError(f"value_norm={self.value_norm!r} must be one of {', '.join(VALUE_NORMS)}")


VALUE_NORMS = ("none", "shared", "all")
"""PPOConfig.value_norm's values."""


@dataclasses.dataclass(frozen=True)
class DQNConfig(AgentConfig):
    """DQN hyperparameters. ``preset("paper")`` gives SPEC section 5 (the paper's Table 3).

    The paper's replay of 400 transitions holds less than one episode of driving,
    so it cannot decorrelate updates; the default keeps 100k transitions. The
    other defaults were tuned on CartPole-v1 (bench/agents_reference.py) and
    checked on the ColourBar image task (bench/agents_image_task.py).
    """

    learning_rate: float = 1e-3
    """Adam learning rate (paper: 1e-4)."""
    buffer_size: int = 100_000
    """replay capacity in transitions (paper: 400, which prevents learning)."""
    batch_size: int = 128
    """minibatch size per gradient step."""
    gamma: float = 0.99
    """discount factor."""
    learning_starts: int = 1_000
    """transitions collected before the first gradient step."""
    train_freq: int = 4
    """env steps between gradient steps."""
    gradient_steps: int = 2
    """gradient steps each time training happens."""
    target_update_interval: int = 250
    """env steps between hard target-network copies."""
    exploration_initial_eps: float = 1.0
    """epsilon at step 0."""
    exploration_final_eps: float = 0.02
    """epsilon after the annealing period."""
    exploration_steps: int = 16_000
    """env steps over which epsilon falls linearly to its final value."""
    max_grad_norm: float = 40.0
    """global gradient-norm clip."""
    huber_delta: float = 10.0
    """TD error beyond which the Huber loss turns linear (RLlib/SB3: 1.0; see the class docstring)."""
    double_q: bool = True
    """pick next actions with the online network (Double DQN; off in the paper preset)."""
    hidden: tuple[int, ...] = (256, 256)
    """MLP hidden sizes for vector observations (images use the Nature CNN)."""
    n_step: int = 1
    """transitions each target spans (multi-step returns, as in Rainbow): the discounted sum of
    up to ``n_step`` rewards of the episode, then ``gamma ** n`` times the bootstrap (shorter at
    an episode's end); 1: the 1-step target of SPEC section 5."""
    demo_margin: float = 0.0
    """Large-margin loss on demonstrated transitions (DQfD, Hester et al. 2018): each one adds
    ``max_a [Q(s, a) + margin * (a != a_E)] - Q(s, a_E)``, averaged over the minibatch's
    demonstrations, so the demonstrator's action a_E outranks the others by ``margin``; 0: off
    (demonstrations, if any, are TD-learned like any transition). DQfD used 0.8."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "default": {},
        # SPEC section 5, Table 3. Unlisted fields keep the defaults above.
        "paper": {
            "learning_rate": 1e-4, "buffer_size": 400, "exploration_final_eps": 0.02, "max_grad_norm": 40.0,
            "huber_delta": 1.0, "double_q": False,
        },
    }

    def __post_init__(self):
        super().__post_init__()
        check_range("learning_rate", self.learning_rate, 0, 1, low_inclusive=False)
        check_range("buffer_size", self.buffer_size, 2)
        check_range("batch_size", self.batch_size, 1)
        check_range("gamma", self.gamma, 0, 1)
        check_range("learning_starts", self.learning_starts, 0)
        check_range("train_freq", self.train_freq, 1)
        check_range("gradient_steps", self.gradient_steps, 1)
        check_range("target_update_interval", self.target_update_interval, 1)
        check_range("exploration_initial_eps", self.exploration_initial_eps, 0, 1)
        check_range("exploration_final_eps", self.exploration_final_eps, 0, 1)
        check_range("exploration_steps", self.exploration_steps, 1)
        check_range("max_grad_norm", self.max_grad_norm, 0, None, low_inclusive=False)
        check_range("huber_delta", self.huber_delta, 0, None, low_inclusive=False)
        check_range("n_step", self.n_step, 1)
        check_range("demo_margin", self.demo_margin, 0)


@dataclasses.dataclass(frozen=True)
class TD3Config(AgentConfig):
    """TD3 hyperparameters. ``preset("paper")`` gives SPEC section 5 (the paper's Table 3).

    The paper's replay of 500 transitions and tau of 0.0002 (a target network
    that moves ~5000x slower than the online one over a short run) prevent
    learning; the default keeps 100k transitions and the usual tau 0.005.
    """

    actor_learning_rate: float = 1e-3
    """Adam learning rate of the actor."""
    critic_learning_rate: float = 1e-3
    """Adam learning rate of the critic(s)."""
    buffer_size: int = 100_000
    """replay capacity in transitions (paper: 500, which prevents learning)."""
    batch_size: int = 128
    """minibatch size per gradient step."""
    gamma: float = 0.99
    """discount factor."""
    tau: float = 0.005
    """Polyak factor of the target networks (paper: 0.0002)."""
    learning_starts: int = 5_000
    """transitions before learning starts (acting uniformly at random until then)."""
    random_steps: int = 0
    """transitions of uniform random actions at the start, per agent (the TD3 paper's
    ``start_timesteps``); the random phase lasts max(random_steps, learning_starts)
    transitions, so 0 keeps the warm-up of ``learning_starts`` alone. Learning starts at
    ``learning_starts`` either way: a longer phase trains the critic on random data first."""
    random_low: tuple[float, ...] = ()
    """lower end of the random phase's uniform draw, per action component (empty: the
    action space's low). The driving presets raise the throttle/brake floor to -0.6:
    drawn over [-1, 1] the car brakes harder (8 m/s^2) than it accelerates (3.5), so it
    stands still most of the phase (docs/guide.md#exploration-that-moves-the-car-ddpg-td3)."""
    train_freq: int = 1
    """env steps between training phases."""
    gradient_steps: int = 1
    """gradient steps per training phase."""
    exploration_noise: float = 0.1
    """std of the Gaussian exploration noise, as a fraction of the action half-range (paper sigma: 0.2)."""
    target_policy_noise: float = 0.2
    """std of the target-policy smoothing noise, as a fraction of the half-range (0 disables)."""
    target_noise_clip: float = 0.5
    """clip of the target-policy smoothing noise, as a fraction of the half-range."""
    policy_delay: int = 2
    """critic updates per actor (and target) update."""
    n_critics: int = 2
    """number of critics; the target uses their minimum."""
    hidden: tuple[int, ...] = (256, 256)
    """hidden sizes of the MLPs (after the Nature CNN for images)."""
    pre_tanh_penalty: float = 0.0
    """weight of the actor's mean squared pre-tanh output in its loss: keeps the tanh
    out of saturation, where its gradient vanishes and the actor sticks at a bound."""
    demo_bc: float = 0.0
    """weight of a behaviour-cloning term on demonstrated transitions (TD3+BC's, Fujimoto and
    Gu 2021, on the demonstrations only): the actor's loss adds ``demo_bc`` times the
    minibatch's mean |Q| (at least 1) times the mean squared distance between its action and
    the demonstrated one, over the minibatch's demonstrations, so ``demo_bc`` is TD3+BC's
    1/alpha whatever the returns' scale (alpha 2.5: 0.4); 0: off (demonstrations, if any, are
    learned like any transition)."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "default": {},
        # SPEC section 5, Table 3. Unlisted fields keep the defaults above.
        "paper": {
            "actor_learning_rate": 1e-3, "critic_learning_rate": 1e-3, "tau": 0.0002,
            "exploration_noise": 0.2, "target_policy_noise": 0.2, "buffer_size": 500,
        },
    }

    def __post_init__(self):
        super().__post_init__()
        check_range("actor_learning_rate", self.actor_learning_rate, 0, 1, low_inclusive=False)
        check_range("critic_learning_rate", self.critic_learning_rate, 0, 1, low_inclusive=False)
        check_range("buffer_size", self.buffer_size, 2)
        check_range("batch_size", self.batch_size, 1)
        check_range("gamma", self.gamma, 0, 1)
        check_range("tau", self.tau, 0, 1, low_inclusive=False)
        check_range("learning_starts", self.learning_starts, 0)
        check_range("random_steps", self.random_steps, 0)
        check_range("train_freq", self.train_freq, 1)
        check_range("gradient_steps", self.gradient_steps, 1)
        check_range("exploration_noise", self.exploration_noise, 0)
        check_range("target_policy_noise", self.target_policy_noise, 0)
        check_range("target_noise_clip", self.target_noise_clip, 0)
        check_range("policy_delay", self.policy_delay, 1)
        check_range("n_critics", self.n_critics, 1)
        check_range("pre_tanh_penalty", self.pre_tanh_penalty, 0)
        check_range("demo_bc", self.demo_bc, 0)


@dataclasses.dataclass(frozen=True)
class DDPGConfig(TD3Config):
    """DDPG hyperparameters: TD3's fields with DDPG's defaults.

    The paper's replay of 500 transitions and tau of 0.002 are the ``paper``
    preset; the default keeps 100k transitions and tau 0.005.
    """

    target_policy_noise: float = 0.0
    """std of the target-policy smoothing noise (0: DDPG has none)."""
    policy_delay: int = 1
    """critic updates per actor update (1: DDPG updates both every step)."""
    n_critics: int = 1
    """number of critics (1: DDPG has no twin critic)."""

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "default": {},
        # SPEC section 5, Table 3. "target noise 0.2" is listed for DDPG in the table,
        # but target-policy smoothing is a TD3 trick; we keep it off so DDPG stays DDPG.
        "paper": {
            "actor_learning_rate": 1e-3, "critic_learning_rate": 1e-3, "tau": 0.002,
            "exploration_noise": 0.2, "policy_delay": 1, "buffer_size": 500,
        },
    }


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
    """Env steps per thread segment between two updates (the n of n-step returns)."""
    vf_coef: float = 0.5
    """Weight of the value loss."""
    ent_coef: float = 0.01
    """Weight of the entropy bonus."""
    max_grad_norm: float = 0.5
    """Global gradient-norm clip applied by each learner thread before its shared step."""
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

    # Fields of the actor-process design (before IMPALA ran on the vector env); checkpoints
    # and config.yaml files written then still carry them: they are dropped on load.
    RETIRED: ClassVar = ("actor_sync_every", "queue_size")

    @classmethod
    def from_dict(cls, values) -> IMPALAConfig:
        return super().from_dict({k: v for k, v in values.items() if k not in cls.RETIRED})

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
