"""Loading a checkpoint for an AC slot of the test (eval/testing/protocol.py): the file is
refused when it cannot drive the slot (:func:`load_for_slot`), and :func:`drive` wraps the
loaded agent in the policy its training variant needs (sampled actions, the nav measurements,
the state vector, K stacked frames, a held action), all read from the checkpoint."""

from __future__ import annotations

from pathlib import Path

from agents.observations import image_space
from eval.testing.protocol import CONTINUOUS, ProtocolError
from eval.testing.rollout import NavPolicy, RepeatPolicy, SampledPolicy, StackedPolicy, StatePolicy


def load_for_slot(path: Path, algo: str, image_size: int = 84):
    """Load the checkpoint given for `algo`'s AC, refusing one that cannot drive it
    (a checkpoint trained on K stacked frames is tested on K, one trained on the nav
    observation with its measurements: :func:`drive`).

    Raises:
        agents.CheckpointError: the file is missing or corrupt.
        ProtocolError: it holds another algorithm, an action space of the other kind
            (a continuous actor in a discrete slot) or another camera size; the
            message names the file.
    """
    import gymnasium

    import agents

    agent = agents.load(path)
    if agent.algo != algo:
        raise ProtocolError(
            f"checkpoint {path} holds a {agent.algo} agent, but it was given for the {algo} AC; "
            f"give it as {agent.algo}, or a {algo} checkpoint for {algo}"
        )
    discrete = isinstance(agent.action_space, gymnasium.spaces.Discrete)
    if discrete != (algo not in CONTINUOUS):
        want = "continuous Box(-1, 1, (2,))" if algo in CONTINUOUS else "discrete Discrete(9)"
        raise ProtocolError(
            f"checkpoint {path} acts in {agent.action_space}, but the {algo} AC needs a {want} "
            "action space; give a checkpoint trained with that action type"
        )
    shape = tuple(image_space(agent.observation_space).shape)
    if obs_of(agent) != "state" and (len(shape) != 3 or shape[:2] != (image_size, image_size)
                                     or shape[2] % 3 or not shape[2]):
        raise ProtocolError(
            f"checkpoint {path} sees observations of shape {shape}, the test environments give "
            f"{(image_size, image_size, 3)} camera images (or K of them stacked, "
            f"{(image_size, image_size, '3K')}); give a checkpoint trained on them"
        )
    return agent


def frame_stack_of(agent) -> int:
    """Camera frames a checkpoint's agent observes at once: its image channels / 3
    (a run trained with ``frame_stack`` K has 84x84x3K images); 1 for the state track."""
    return 1 if obs_of(agent) == "state" else int(image_space(agent.observation_space).shape[-1]) // 3


def obs_of(agent) -> str:
    """The observation variant a checkpoint's agent was trained on (``cosim train --obs``):
    "nav" for a ``Dict(image, measurements)`` observation space, "state" for a vector
    (agents.base.observation_variant), else "image"."""
    from agents.base import observation_variant

    return observation_variant(agent.observation_space)


def drive(agent, sample_seed: int | None = None, env=None, slot: str | None = None):
    """The policy of one AC from a loaded checkpoint: the agent itself (or, with
    ``sample_seed``, a :class:`~eval.testing.rollout.SampledPolicy` drawing its actions) for
    one frame; for a nav-trained agent inside a :class:`~eval.testing.rollout.NavPolicy` that
    builds the measurements of AC ``slot`` of ``env``; inside a
    :class:`~eval.testing.rollout.StackedPolicy` with that AC's own frame history when it was
    trained on K frames; inside a :class:`~eval.testing.rollout.RepeatPolicy` that holds each
    action for the checkpoint's ``action_repeat`` steps when it was trained with one. All read
    from the checkpoint, so ACs of every variant share one test environment.

    Raises:
        ProtocolError: a nav-trained agent without the env and slot it drives.
    """
    k = frame_stack_of(agent)
    policy = agent if sample_seed is None else SampledPolicy(agent, sample_seed)
    if obs_of(agent) == "nav":
        if env is None or slot is None:
            raise ProtocolError(f"{agent.algo} was trained with --obs nav: give drive() the test env and "
                                "the AC slot it drives, to build that AC's measurements")
        policy = NavPolicy(policy, env, slot)
    if obs_of(agent) == "state":  # its own state vector, from the shared test env's world
        if env is None or slot is None:
            raise ProtocolError(f"{agent.algo} was trained with --obs state: give drive() the test env and "
                                "the AC slot it drives, to build that AC's state vector")
        policy = StatePolicy(policy, env, slot)
    policy = StackedPolicy(policy, k) if k > 1 else policy
    return RepeatPolicy(policy, repeat) if (repeat := action_repeat_of(agent)) > 1 else policy


def action_repeat_of(agent) -> int:
    """Environment steps a checkpoint's agent holds each action for (its config's
    ``action_repeat``; 1 for a checkpoint written before the option)."""
    return int(getattr(getattr(agent, "config", None), "action_repeat", 1))

