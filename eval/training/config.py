"""Training configuration: :class:`TrainConfig`, resolved from a preset by
:func:`make_config`, with ``--set FIELD=VALUE`` hyperparameter changes
(:func:`parse_set`, :func:`parse_hyper`).

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
from cosim.errors import CosimError
from cosim.wrappers import OBS_VARIANTS
from eval.training.presets import load_presets

__all__ = ["ALGORITHMS", "ASYNC_ALGOS", "COLLISION_RULES", "CONTINUOUS_ALGOS", "DEMO_ALGOS", "DEMO_HYPER",
           "DEMO_UPDATES", "DISCRETE_ALGOS", "OBS_VARIANTS", "TrainConfig", "TrainError", "make_config", "parse_hyper", "parse_set"]

ALGORITHMS: tuple[str, ...] = tuple(registry.ALGORITHMS)
DISCRETE_ALGOS = registry.DISCRETE
CONTINUOUS_ALGOS = registry.CONTINUOUS
ASYNC_ALGOS = registry.ASYNC
COLLISION_RULES = ("event", "step", "end")
"""``--collisions``: ``event`` (the default, the test's rule): the episode goes on after a
collision and each collision event is charged once; ``step``: the episode goes on and every
contact step is charged (task version 3); ``end``: a collision ends the AC's training episode
(the paper's rule). TrainConfig.collision_charge and .collisions_end_episode; docs/task.md,
"Collision rule"."""


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


class TrainError(CosimError, ValueError):
    """A training request that cannot run; the message says what to change."""


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
    """Threads running the ACs' updates at once (agents.loop.run_vector_loop; each AC has its
    own networks, so the result is the same for any value); 0: one per AC up to the CPUs
    (OMP_NUM_THREADS when set, as Ray sets it per trial)."""
    frame_stack: int = 1
    """Camera frames per observation, stacked on the channel axis oldest first (84x84x3K;
    1: the paper's single frame). The training env stacks them (cosim.wrappers.FrameStack)
    and every test of a checkpoint does too, read from its observation shape."""
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

    validation_episodes: int = 0
    """Held-out episodes the run's ACs drive under the test's rules at every checkpoint; each
    AC's best.pt is its checkpoint with the highest mean validation return (eval/training/validation.py;
    docs/task.md, "Checkpoint selection"). 0: no validation, best.pt by training return (also
    what a config.yaml written before the option reads as). make_config gives 2."""
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


def make_config(algo: str, env: str = "env_1", preset: str = "quick", *, agents: int | None = None,
                steps: int | None = None, seed: int = 0, action_type: str | None = None,
                image_size: int = 84, agent_preset: str | None = None,
                hyper: Mapping[str, str] | None = None, envs: int | None = None, device: str = "auto",
                torch_threads: int = 0, frame_stack: int | None = None, obs: str = "image",
                learner_threads: int = 0, collisions: str = "event",
                validation_episodes: int | None = None, validation_steps: int | None = None,
                share_params: bool = False, init_from: str | Path | None = None,
                stall_truncate: int = 0, demo_steps: int = 0, demo_updates: int = 0) -> TrainConfig:
    """Resolve a training request into a TrainConfig, refusing what cannot work.

    ``hyper`` changes agent hyperparameters last, field name -> value as text
    (``cosim train --set actor_learning_rate=1e-4``). ``envs`` and ``frame_stack``
    default to the preset's (for A3C and IMPALA ``envs`` defaults to the preset's
    ``workers``: A3C runs one learner thread per environment, IMPALA acts in all).
    ``validation_episodes`` / ``validation_steps``: the held-out episodes that pick each AC's
    best.pt (TrainConfig.validation_episodes; 0 episodes: by training return).
    ``collisions``: "event" (the default, the test's rule: the episode goes on and each collision
    event is charged once), "step" (every contact step charged) or "end" (a collision ends the
    AC's training episode, the paper's).
    ``obs``: "image" (the default), "nav" or "state" (TrainConfig.obs; "state" takes frame stack 1
    and the preset's ``state_hidden`` MLP sizes). ``share_params``: one network for
    all the run's ACs (TrainConfig.share_params). ``init_from``: a run folder or checkpoint to
    warm-start from (TrainConfig.init_from). ``stall_truncate``: TrainConfig.stall_truncate.
    ``demo_steps``, ``demo_updates``: autopilot demonstrations in the replay (TrainConfig.demo_steps).

    Raises:
        TrainError: unknown algorithm or preset (listing the valid ones), an action
            type the algorithm cannot use (with the reason), bad numbers.
        cosim.errors.ScenarioError: unknown environment (listing the valid ones).
    """
    from cosim.scenario import load_scenario

    if algo not in ALGORITHMS:
        raise TrainError(f"unknown algorithm {algo!r}; choose one of {', '.join(ALGORITHMS)} (or 'all')")
    presets = load_presets()
    if preset not in presets:
        raise TrainError(f"unknown preset {preset!r}; choose one of {', '.join(presets)}")
    natural = "discrete" if algo in DISCRETE_ALGOS else "continuous"
    if action_type is not None and action_type != natural:
        why = ("it picks among a finite set of actions (Discrete(9))" if natural == "discrete"
               else "its actor outputs continuous values (Box(-1, 1, (2,)))")
        raise TrainError(
            f"{algo} cannot train with {action_type} actions: {why}; use --action-type {natural} "
            f"or a {'continuous' if natural == 'discrete' else 'discrete'} algorithm "
            f"({', '.join(CONTINUOUS_ALGOS if natural == 'discrete' else DISCRETE_ALGOS)})"
        )
    scenario = load_scenario(env)
    p = presets[preset]
    n = p.agents if agents is None else int(agents)
    if not 1 <= n <= scenario.max_agents:
        raise TrainError(f"--agents must be 1..{scenario.max_agents} for {env}, got {n}")
    total = p.steps[algo] if steps is None else int(steps)
    if total < 1:
        raise TrainError(f"--steps must be >= 1, got {total}")
    if envs is None:  # A3C and IMPALA: the preset's workers, one environment (and A3C thread) each
        envs = p.envs if algo not in ASYNC_ALGOS else p.workers
    if obs == "state" and frame_stack is not None and int(frame_stack) != 1:
        raise TrainError(f"--frame-stack {frame_stack} stacks camera frames; --obs state observes one "
                         "state vector (it carries the speeds): drop --frame-stack or give 1")
    # the state track observes one vector: the preset's frame stack is the camera's
    frame_stack = (1 if obs == "state" else p.frame_stack) if frame_stack is None else int(frame_stack)
    if frame_stack < 1:
        raise TrainError(f"--frame-stack must be >= 1 (1: a single camera frame), got {frame_stack}")
    if int(envs) < 1 or int(torch_threads) < 0 or int(learner_threads) < 0:
        raise TrainError(f"--envs must be >= 1, --torch-threads and --learner-threads >= 0, got "
                         f"{envs}, {torch_threads} and {learner_threads}")
    if validation_episodes is None:
        validation_episodes = VALIDATION_EPISODES if p.validation_episodes is None else p.validation_episodes
    # the preset's episode length, at most the test's (the scenario's horizon): docs/task.md
    validation_steps = min(p.horizon, scenario.horizon) if validation_steps is None else int(validation_steps)
    validation_episodes = int(validation_episodes)
    if validation_episodes < 0 or validation_steps < 1:
        raise TrainError(f"--validation-episodes must be >= 0 (0: off) and --validation-steps >= 1, got "
                         f"{validation_episodes} and {validation_steps}")
    if obs not in OBS_VARIANTS:
        raise TrainError(f"--obs must be {' or '.join(OBS_VARIANTS)}, got {obs!r}")
    if collisions not in COLLISION_RULES:
        raise TrainError(f"--collisions must be {' or '.join(COLLISION_RULES)}, got {collisions!r}")
    if device not in ("auto", "cpu", "cuda"):
        raise TrainError(f"--device must be auto, cpu or cuda, got {device!r}")
    _check_variants(algo, share_params, int(stall_truncate), int(demo_steps), int(demo_updates))
    config_cls = registry.get_config_class(algo)  # PPOConfig, ... (agents/configs.py, no torch)
    chosen = agent_preset or p.agent_preset
    try:  # the preset's typed config (with its YAML's changes), then the --set changes
        # the state track's MLPs: the preset's state_hidden, unless the algorithm's YAML sets hidden
        state = {"hidden": tuple(p.state_hidden)} if obs == "state" else {}
        base = config_cls.preset(chosen, **{"reward_scale": p.reward_scale, **state, **p.overrides.get(algo, {})})
        agent_config = base.replace(**parse_hyper(base, hyper or {}, algo))
    except ValueError as exc:
        raise TrainError(f"{algo} hyperparameters: {exc}") from exc
    return TrainConfig(
        algo=algo, env=env, agents=n, steps=total, seed=int(seed), preset=preset,
        horizon=p.horizon, checkpoint_every=min(p.checkpoint_every, total), workers=p.workers,
        image_size=int(image_size), agent_config=agent_config, envs=int(envs), device=device,
        torch_threads=int(torch_threads), frame_stack=frame_stack, obs=obs,
        learner_threads=int(learner_threads),
        collisions_end_episode=collisions == "end",
        collision_charge="step" if collisions == "step" else "event",
        validation_episodes=validation_episodes,
        validation_steps=validation_steps, policy_dtype=p.policy_dtype, share_params=bool(share_params),
        init_from=_init_source(init_from), stall_truncate=int(stall_truncate),
        demo_steps=int(demo_steps), demo_updates=int(demo_updates),
    )


def _check_variants(algo: str, share_params: bool, stall_truncate: int, demo_steps: int, demo_updates: int) -> None:
    """Refuse a training variant the algorithm cannot run (make_config), naming the option."""
    if stall_truncate < 0:
        raise TrainError(f"--stall-truncate must be >= 0 steps (0: off), got {stall_truncate}")
    if demo_steps < 0 or demo_updates < 0:
        raise TrainError(f"--demo-steps and --demo-updates must be >= 0 (0: off), got {demo_steps} and {demo_updates}")
    if demo_steps and algo not in DEMO_ALGOS:
        raise TrainError(f"--demo-steps fills a replay buffer: {', '.join(DEMO_ALGOS)} only, not {algo}")
    if demo_updates and not demo_steps:
        raise TrainError("--demo-updates pre-trains on the demonstrations: give them with --demo-steps N")
    if share_params and algo in ASYNC_ALGOS:
        raise TrainError(f"--share-params is for {', '.join(a for a in ALGORITHMS if a not in ASYNC_ALGOS)}; "
                         f"{algo} builds its own learners: drop --share-params for it")


def _init_source(init_from: str | Path | None) -> str | None:
    """``--init-from`` as an absolute path, refused when it holds no checkpoint."""
    if init_from is None:
        return None
    path = Path(init_from).resolve()
    if not (path.is_file() or (path / "checkpoints" / "ac_0" / "best.pt").is_file()):
        raise TrainError(f"--init-from {path}: not a checkpoint file nor a run folder with "
                         "checkpoints/ac_0/best.pt; name a finished run of the same algorithm and --obs")
    return str(path)


def parse_set(items: list[str]) -> dict[str, str]:
    """``["lr=3e-4", ...]`` (``--set`` arguments) -> ``{"lr": "3e-4"}``; values stay text."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise TrainError(f"--set {item!r}: write FIELD=VALUE, e.g. --set learning_rate=3e-4")
        out[key.strip()] = value.strip()
    return out


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
