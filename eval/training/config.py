"""Training configuration: :class:`TrainConfig`, what a run trains with, resolved by
:func:`resolve` from a run's options (eval.training.options.RunOptions, the one declaration of
them) and its preset; :func:`make_config` takes the options as keywords; ``--set FIELD=VALUE``
hyperparameter changes are typed by :func:`parse_hyper`.

Algorithm names, action kinds and training loops come from the catalogue
(agents/registry.py); presets from eval/training/presets.py. A TrainConfig holds its
algorithm's typed hyperparameters (``agent_config``, a ``PPOConfig`` ... from the torch-free
agents/configs.py), which :func:`make_config` builds and training hands to the algorithm's
constructor unchanged (docs/design.md, "One hyperparameter from the command line to the
optimiser").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from agents import registry
from agents.configs import AgentConfig
from cosim.wrappers import OBS_VARIANTS
from eval.training.options import COLLISION_RULES, RunOptions, TrainError, parse_set
from eval.training.presets import load_presets

__all__ = ["ALGORITHMS", "ASYNC_ALGOS", "COLLISION_RULES", "CONTINUOUS_ALGOS", "DEMO_ALGOS", "DEMO_HYPER",
           "DEMO_UPDATES", "DISCRETE_ALGOS", "OBS_VARIANTS", "RunOptions", "TrainConfig", "TrainError", "make_config",
           "parse_hyper", "parse_set", "resolve"]

ALGORITHMS: tuple[str, ...] = tuple(registry.ALGORITHMS)
DISCRETE_ALGOS = registry.DISCRETE
CONTINUOUS_ALGOS = registry.CONTINUOUS
ASYNC_ALGOS = registry.ASYNC
DEMO_UPDATES = 2000
"""Pre-training gradient steps per AC of the demonstration variant (`cosim benchmark
--demo-steps`), as the demonstration pilot's (task version 3; in git history at 1b59d82, docs/results/2026-11-26-demo-pilot)."""

DEMO_HYPER: dict[str, dict[str, str]] = {
    "dqn": {"demo_margin": "0.8", "exploration_initial_eps": "0.1"},
    "ddpg": {"demo_bc": "1.0"},
    "td3": {"demo_bc": "1.0"},
}
"""The demonstration variant's losses and exploration per replay learner (`cosim benchmark
--demo-steps`; docs/agents.md, "Demonstrations"): DQN with DQfD's margin 0.8 and epsilon from
0.1 (its pre-trained policy already drives), DDPG and TD3 with the behaviour-cloning term at
TD3+BC's scale, weight 1 (alpha 1)."""

DEMO_ALGOS = tuple(DEMO_HYPER)
"""The replay learners, which ``--demo-steps`` can fill with autopilot demonstrations."""


VALIDATION_EPISODES = 2
"""Validation episodes per checkpoint unless ``--validation-episodes`` says otherwise."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (written to config.yaml)."""

    algo: str
    env: str = "env_1"
    agents: int = 3
    steps: int = 10_000
    seed: int = 0
    preset: str = "quick"
    horizon: int = 300
    """Steps per training episode: :func:`resolve` gives the preset's (TrainPreset.horizon)."""
    checkpoint_every: int = 2_000
    workers: int = 2
    """The preset's default ``envs`` for A3C and IMPALA (recorded; ``envs`` is what runs)."""
    image_size: int = 84
    agent_config: AgentConfig | None = None
    """The algorithm's hyperparameters, its config class from the catalogue
    (``agents.registry.get_config_class``: a ``PPOConfig`` for PPO, ...), handed to the agents'
    constructor as it is. Given as a mapping (its serialised form: config.yaml, pbt.json, a Ray
    trial's config) it is built into that class here (``from_dict``, which checks every key and
    value); None: the class's defaults. ``to_dict`` writes it back as a mapping."""
    envs: int = 1
    """Environments stepped together (one vector env, agents/vector.py), each in its own
    process when > 1; every algorithm (A3C: one learner thread per environment)."""
    device: str = "auto"
    """Torch device of the learners: auto (cuda when available), cpu or cuda."""
    torch_threads: int = 0
    """torch.set_num_threads in the trainer; 0: the CPUs left beside the env workers (all
    with one env) divided among the learner threads, at least 1 (A3C: 1)."""
    learner_threads: int = 0
    """Threads running the ACs' updates at once (agents.loop.run_loop; each AC has its
    own networks, so the result is the same for any value); 0: one per AC up to the CPUs
    (OMP_NUM_THREADS when set, as Ray sets it per trial)."""
    frame_stack: int = 1
    """Camera frames per observation, stacked on the channel axis oldest first (84x84x3K;
    1: the paper's single frame). The training env stacks them (cosim.wrappers.FrameStack)
    and every test of a checkpoint does too, read from its observation shape. :func:`resolve`
    gives the preset's (runs.yaml, the one source of the default) unless ``--frame-stack`` says;
    1 here is what a config.yaml without the key (written before frame stacks) reads as."""
    obs: str = "image"
    """What an AC observes: ``image``, its camera frames (the paper's observation), or ``nav``,
    those beside the measurements vector (speed, route command, distance to the goal;
    cosim.wrappers.NavObservation), or ``state``, the state track: a 65-number vector with the
    cameras off (cosim.state; frame_stack 1, MLPs of the preset's ``state_hidden``). Checkpoints
    record it as their observation space (Box or Dict), and every test of a checkpoint builds it
    for that AC (docs/task.md, "Observation")."""
    collisions_end_episode: bool = False
    """False (the default, ``--collisions event`` or ``step``): the test's rule, the episode goes
    on after a collision until the goal, leaving the region or the horizon. True (``--collisions
    end``): a collision ends the AC's training episode (the paper's training protocol), which
    makes crashing worth more than waiting when 71 or more steps remain (docs/task.md,
    "Collision rule")."""
    collision_charge: str = "event"
    """``event`` (the default): the collision weight once per collision event; ``step``
    (``--collisions step``): every contact step (cosim.scenario.Contact.charge)."""
    collision_fault: str = "at_fault"
    """Who of a vehicle contact the reward charges: ``at_fault`` (the default since task version
    5) or ``both`` (``--fault both``, task version 4; cosim.scenario.Contact.fault)."""

    validation_episodes: int = 0
    """Held-out episodes the run's ACs drive under the test's rules at every checkpoint; each
    AC's best.pt is its checkpoint with the highest mean validation score (``select_by``; eval/training/validation.py;
    docs/task.md, "Checkpoint selection"). 0: no validation, best.pt by training return (also
    what a config.yaml written before the option reads as). make_config gives 2."""
    select_by: str = "return"
    """What picks each AC's best.pt among its validated checkpoints: ``return``, the mean
    undiscounted return over the validation episodes (the default, and what a config.yaml written
    before the option reads as), or ``ds`` (``--select-by ds``), the mean driving score. Ties under
    ``ds`` go to the later checkpoint (the score is bounded, and 0 or 1 on every episode is common)."""
    validation_steps: int = 300
    """Steps per validation episode. make_config gives the preset's horizon, at most the
    scenario's (the test's episode length): quick 300, standard and paper 600, so a checkpoint
    of a slot whose goal takes the autopilot 300-530 steps is judged on reaching it."""
    share_params: bool = False
    """False (the default, the paper's setting): every AC has its own networks and learns from its
    own car's transitions. True (``--share-params``): the run's ACs act with ONE network that
    learns from all their transitions (agents/shared.py; docs/agents.md, "Parameter sharing");
    every AC's checkpoint holds that network. PPO, DQN, DDPG and TD3 only."""
    init_from: str | None = None
    """None (the default): every network starts from random weights. A run folder or a
    checkpoint file (``--init-from``): a warm start, each AC's policy networks copied from it
    (a run folder: the source's checkpoints/ac_k/best.pt, ac_0's where it has no ac_k) before
    training, optimizers and schedules fresh (agents.checkpoint.warm_start; docs/agents.md,
    "Warm start"). Stored as an absolute path."""
    stall_truncate: int = 0
    """0 (the default, the test's rule): an episode runs to its goals or the horizon. N > 0
    (``--stall-truncate N``): a training episode is truncated once every AC has stood still for
    N steps away from a red light (cosim.scenario.Termination.stall_truncate), so the ACs get
    more attempts per env step; the rewards are the test's (docs/task.md, Collision rule)."""
    demo_steps: int = 0
    """0 (the default): no demonstrations. N > 0 (``--demo-steps N``, DQN, DDPG and TD3): before
    its first env step the run drives at least N env steps (whole episodes, seeds apart from
    training's) with the scripted autopilot, its discrete form for DQN, and stores every AC's
    transitions in that AC's replay as demonstrations (Agent.observe_demonstration; DQfD,
    Hester et al. 2018). They are not counted in ``steps`` nor in the agents' exploration
    schedule; a resumed run drives them again (the replay is not checkpointed)
    (eval/training/demos.py; docs/agents.md, "Demonstrations")."""
    demo_updates: int = 0
    """With ``demo_steps``: gradient steps on the demonstrations alone before the first env
    step (DQfD's pre-training; ``--demo-updates``); 0: none. Not repeated on resume."""
    policy_dtype: str = "float32"
    """How each AC's best.pt stores its float weights: float32 (exact) or float16 (half the
    bytes, rounded; the smoke preset's): the preset's policy_dtype (eval/training/presets.py)."""
    encoder: str | None = None
    """None (the default): the networks see camera frames and learn their CNN end to end. A
    frozen perception encoder file (``--encoder``, built by `cosim encoder train`; an absolute
    path): each AC observes the encoder's 512 features of each of its ``frame_stack`` frames,
    concatenated oldest first, and every algorithm learns MLP heads (the preset's
    ``state_hidden``) on them (eval/training/encoder.py ``observation``; docs/task.md, "The
    frozen perception encoder")."""
    encoder_sha256: str | None = None
    """The SHA-256 of the ``encoder`` file when the run was resolved: a resume, and every test
    of the run's checkpoints, refuses an encoder file with another hash."""

    def __post_init__(self):
        try:
            config_class = registry.get_config_class(self.algo)
        except KeyError:
            raise TrainError(f"unknown algorithm {self.algo!r}; choose one of {', '.join(ALGORITHMS)}") from None
        agent_config = self.agent_config
        if agent_config is None or isinstance(agent_config, Mapping):  # deserialising
            try:
                agent_config = config_class.from_dict(agent_config or {})
            except (TypeError, ValueError) as exc:
                raise TrainError(f"'agent_config': {exc}") from None
            object.__setattr__(self, "agent_config", agent_config)
        elif type(agent_config) is not config_class:
            raise TrainError(f"'agent_config': {self.algo}'s config class is {config_class.__name__}, "
                             f"got a {type(agent_config).__name__}")

    @property
    def action_type(self) -> str:
        return "discrete" if self.algo in DISCRETE_ALGOS else "continuous"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def make_config(algo: str, env: str = "env_1", preset: str = "quick", **options: Any) -> TrainConfig:
    """Resolve a training request into a TrainConfig, refusing what cannot work: :func:`resolve`
    of ``RunOptions(algo=algo, env=env, preset=preset, **options)``, the keywords being the
    options' names (eval/training/options.py: ``agents``, ``steps``, ``frame_stack``, ``hyper``,
    ...; ``hyper`` maps hyperparameter names to values as text, as ``--set`` gives them).

    Raises:
        TrainError: an option the declaration refuses (naming its flag), or what :func:`resolve`
            refuses.
        cosim.errors.ScenarioError: unknown environment (listing the valid ones).
    """
    return resolve(RunOptions(algo=algo, env=env, preset=preset, **options))


def resolve(options: RunOptions) -> TrainConfig:
    """The TrainConfig of one run's options: what the options leave open comes from the preset.

    ``envs`` and ``frame_stack`` default to the preset's (for A3C and IMPALA ``envs`` defaults to
    the preset's ``workers``: A3C runs one learner thread per environment, IMPALA acts in all);
    ``--obs state`` takes frame stack 1 and the preset's ``state_hidden`` MLP sizes, as ``--encoder``
    takes those MLP sizes (its file's hash recorded).
    ``validation_episodes`` defaults to the preset's, else :data:`VALIDATION_EPISODES`;
    ``validation_steps`` to the preset's horizon, at most the scenario's (the test's episode length).
    ``collisions`` sets TrainConfig.collisions_end_episode and .collision_charge; ``hyper``
    changes agent hyperparameters last.

    Raises:
        TrainError: ``--algo all`` (resolve each algorithm's options: RunOptions.for_algo), unknown
            preset (listing the valid ones), an action type the algorithm cannot use (with the
            reason), a variant the algorithm cannot run, a bad hyperparameter, --init-from without
            a checkpoint, --encoder without a file or with --obs nav or state.
        cosim.errors.ScenarioError: unknown environment (listing the valid ones).
    """
    from cosim.scenario import load_scenario

    o = options
    if o.algo == "all":
        raise TrainError("--algo all trains every algorithm: resolve the options of each (RunOptions.for_algo)")
    presets = load_presets()
    if o.preset not in presets:
        raise TrainError(f"unknown preset {o.preset!r}; choose one of {', '.join(presets)}")
    _check_action_type(o.algo, o.action_type)
    scenario = load_scenario(o.env)
    p = presets[o.preset]
    n = p.agents if o.agents is None else o.agents
    if not 1 <= n <= scenario.max_agents:
        raise TrainError(f"--agents must be 1..{scenario.max_agents} for {o.env}, got {n}")
    total = p.steps[o.algo] if o.steps is None else o.steps
    envs = o.envs
    if envs is None:  # A3C and IMPALA: the preset's workers, one environment (and A3C thread) each
        envs = p.envs if o.algo not in ASYNC_ALGOS else p.workers
    if o.obs == "state" and o.frame_stack is not None and o.frame_stack != 1:
        raise TrainError(f"--frame-stack {o.frame_stack} stacks camera frames; --obs state observes one state "
                         "vector (it carries the speeds): drop --frame-stack or give 1")
    # the state track observes one vector: the preset's frame stack is the camera's
    frame_stack = (1 if o.obs == "state" else p.frame_stack) if o.frame_stack is None else o.frame_stack
    validation_episodes = o.validation_episodes
    if validation_episodes is None:
        validation_episodes = VALIDATION_EPISODES if p.validation_episodes is None else p.validation_episodes
    # the preset's episode length, at most the test's (the scenario's horizon): docs/task.md
    validation_steps = min(p.horizon, scenario.horizon) if o.validation_steps is None else o.validation_steps
    _check_variants(o.algo, o.share_params, o.stall_truncate, o.demo_steps, o.demo_updates)
    encoder, encoder_sha256 = _encoder_source(o.encoder, o.obs)
    config_cls = registry.get_config_class(o.algo)  # PPOConfig, ... (agents/configs.py, no torch)
    try:  # the preset's typed config (with its YAML's changes), then the --set changes
        # the state track's MLPs: the preset's state_hidden, unless the algorithm's YAML sets hidden
        # (and a frozen encoder's features: a vector, as the state)
        state = {"hidden": tuple(p.state_hidden)} if o.obs == "state" or encoder else {}
        track = p.state_overrides.get(o.algo, {}) if o.obs == "state" else {}  # the state track's own
        base = config_cls.preset(o.agent_preset or p.agent_preset,
                                 **{"reward_scale": p.reward_scale, **state, **p.overrides.get(o.algo, {}), **track})
        agent_config = base.replace(**parse_hyper(base, o.hyper, o.algo))
    except ValueError as exc:
        raise TrainError(f"{o.algo} hyperparameters: {exc}") from exc
    return TrainConfig(
        algo=o.algo, env=o.env, agents=n, steps=total, seed=o.seed, preset=o.preset,
        horizon=p.horizon, checkpoint_every=min(p.checkpoint_every, total), workers=p.workers,
        agent_config=agent_config, envs=envs, device=o.device, torch_threads=o.torch_threads,
        frame_stack=frame_stack, obs=o.obs, learner_threads=o.learner_threads,
        collisions_end_episode=o.collisions == "end", collision_charge="step" if o.collisions == "step" else "event",
        collision_fault=o.fault,
        validation_episodes=validation_episodes, validation_steps=validation_steps, select_by=o.select_by,
        policy_dtype=p.policy_dtype,
        share_params=o.share_params, init_from=_init_source(o.init_from), stall_truncate=o.stall_truncate,
        demo_steps=o.demo_steps, demo_updates=o.demo_updates, encoder=encoder, encoder_sha256=encoder_sha256,
    )


def _check_action_type(algo: str, action_type: str | None) -> None:
    """Refuse ``--action-type`` of the other kind than ``algo``'s, saying why and what to use."""
    natural = "discrete" if algo in DISCRETE_ALGOS else "continuous"
    if action_type is not None and action_type != natural:
        why = ("it picks among a finite set of actions (Discrete(9))" if natural == "discrete"
               else "its actor outputs continuous values (Box(-1, 1, (2,)))")
        raise TrainError(
            f"{algo} cannot train with {action_type} actions: {why}; use --action-type {natural} "
            f"or a {'continuous' if natural == 'discrete' else 'discrete'} algorithm "
            f"({', '.join(CONTINUOUS_ALGOS if natural == 'discrete' else DISCRETE_ALGOS)})"
        )


def _check_variants(algo: str, share_params: bool, stall_truncate: int, demo_steps: int, demo_updates: int) -> None:
    """Refuse a training variant the algorithm cannot run (make_config), naming the option."""
    if demo_steps and algo not in DEMO_ALGOS:
        raise TrainError(f"--demo-steps fills a replay buffer: {', '.join(DEMO_ALGOS)} only, not {algo}")
    if demo_updates and not demo_steps:
        raise TrainError("--demo-updates pre-trains on the demonstrations: give them with --demo-steps N")
    if share_params and algo in ASYNC_ALGOS:
        raise TrainError(f"--share-params is for {', '.join(a for a in ALGORITHMS if a not in ASYNC_ALGOS)}; "
                         f"{algo} builds its own learners: drop --share-params for it")


NOT_CAMERA = ("nav", "state")
"""The ``--obs`` variants a frozen encoder cannot take: the state vector has no camera frame, and
``nav`` joins its frames to measurements in a Dict (an encoder with it is left for later)."""


def _encoder_source(encoder: str | Path | None, obs: str) -> tuple[str | None, str | None]:
    """``--encoder`` as an absolute path and its file's SHA-256, refused with a variant that has
    no camera frames of its own (:data:`NOT_CAMERA`) or without a file."""
    if encoder is None:
        return None, None
    if obs in NOT_CAMERA:
        what = "gives no camera frames (cameras off)" if obs == "state" else "joins the frames to measurements"
        cameras = " or ".join(v for v in OBS_VARIANTS if v not in NOT_CAMERA)
        raise TrainError(f"--encoder encodes camera frames; --obs {obs} {what}: use --obs {cameras} with "
                         "--encoder, or drop --encoder")
    path = Path(encoder).resolve()
    if not path.is_file():
        raise TrainError(f"--encoder {path}: no such file; build one with `cosim encoder train --out {path}`")
    import hashlib

    with open(path, "rb") as f:
        return str(path), hashlib.file_digest(f, "sha256").hexdigest()


def _init_source(init_from: str | Path | None) -> str | None:
    """``--init-from`` as an absolute path, refused when it holds no checkpoint."""
    if init_from is None:
        return None
    path = Path(init_from).resolve()
    if not (path.is_file() or (path / "checkpoints" / "ac_0" / "best.pt").is_file()):
        raise TrainError(f"--init-from {path}: not a checkpoint file nor a run folder with "
                         "checkpoints/ac_0/best.pt; name a finished run of the same algorithm and --obs")
    return str(path)


def parse_hyper(current: AgentConfig, hyper: Mapping[str, str], algo: str) -> dict[str, Any]:
    """Typed values for hyperparameter overrides given as text, checked against the fields of
    ``current`` (an algorithm's config, e.g. a ``PPOConfig``), for ``current.replace(**...)``.

    A value must have the type of the field's current value; ints are accepted for
    floats and lists for tuples. (YAML reads "1e-4" as text, hence float().)

    Raises:
        ValueError: an unknown field (listing the valid ones) or a value of the wrong type.
    """
    names = [f.name for f in dataclasses.fields(current)]
    out: dict[str, Any] = {}
    for key, text in hyper.items():
        if key not in names:
            raise ValueError(f"--set {key}: {algo} has no such hyperparameter; valid: {', '.join(sorted(names))}")
        old = getattr(current, key)
        try:
            value = yaml.safe_load(text)
            if isinstance(old, float) and not isinstance(value, bool):
                value = float(value)
            elif isinstance(old, tuple) and isinstance(value, list):
                value = tuple(value)
            ok = type(value) is type(old)
        except (TypeError, ValueError, yaml.YAMLError):
            ok = False
        if not ok:
            kind = type(old).__name__
            raise ValueError(
                f"--set {key}={text}: expected {'an' if kind[0] in 'aeiou' else 'a'} {kind} like {old!r}"
            )
        out[key] = value
    return out
