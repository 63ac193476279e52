"""Loading a checkpoint for an AC slot of the test (eval/testing/protocol.py): the file is
refused when it cannot drive the slot (:func:`load_for_slot`), and :func:`drive` wraps the
loaded agent in the policy its training variant needs (sampled actions, the nav measurements,
the state vector, K stacked frames, a frozen encoder's features, a held action), all read from
the checkpoint and, for the encoder, from its run folder's config.yaml (:func:`frame_encoder`)."""

from __future__ import annotations

import functools
from pathlib import Path

from agents.observations import image_space
from cosim.state import STATE_DIM, is_state_space
from eval.testing.protocol import CONTINUOUS, ProtocolError
from eval.testing.rollout import (
    EncodedPolicy,
    NavPolicy,
    RepeatPolicy,
    SampledPolicy,
    StackedPolicy,
    StatePolicy,
)


def run_config(checkpoint: Path) -> dict:
    """The config.yaml of the run folder a checkpoint lies in; {} for a file outside a run
    folder or an unreadable config."""
    import yaml

    from eval.testing.checkpoints import run_of

    run = run_of(Path(checkpoint))
    try:
        cfg = yaml.safe_load((run / "config.yaml").read_text()) if run is not None else None
    except (OSError, yaml.YAMLError):
        cfg = None
    return cfg if isinstance(cfg, dict) else {}


def encoder_record(checkpoint: Path) -> tuple[str, str] | None:
    """The frozen encoder a checkpoint's run trained on: ``(path, sha256)`` from its run
    folder's config.yaml (``encoder``, ``encoder_sha256``: `cosim train --encoder`); None for a
    run without one, or a file outside a run folder."""
    cfg = run_config(checkpoint)
    if not cfg.get("encoder"):
        return None
    return str(cfg["encoder"]), str(cfg.get("encoder_sha256") or "")


def draws_route(checkpoint: Path) -> bool:
    """Whether a checkpoint's run trained on the route camera (``cosim train --obs route``, its
    config.yaml's ``obs``): its observation space is the plain camera's, so only the run folder
    says it. A route checkpoint copied out of its run folder is tested on the plain camera."""
    return run_config(checkpoint).get("obs") == "route"


@functools.lru_cache(maxsize=8)
def _load_encoder(path: str, sha256: str):
    from agents.encoder import load_encoder

    return load_encoder(path, sha256)


def frame_encoder(checkpoint: Path, given: Path | str | None = None):
    """The frozen encoder (agents.encoder.FrozenEncoder) whose features a checkpoint's AC
    observes, or None when its run trained on frames: the file ``given`` (`cosim test
    --encoder`), else the one its run recorded, which must have the hash the run recorded.

    Raises:
        ProtocolError: the file is missing, has another hash than the run's (another encoder,
            or the same path rebuilt) or is no encoder; the message names the checkpoint, the
            file and the fix.
    """
    from agents.encoder import EncoderError, file_sha256

    record = encoder_record(checkpoint)
    if record is None:
        return None
    recorded, sha = record
    file = Path(given) if given is not None else Path(recorded)
    trained = f"checkpoint {checkpoint} was trained on the frozen encoder {recorded} (sha256 {sha[:12]})"
    if not file.is_file():
        raise ProtocolError(f"{trained}, and {file} does not exist; give `cosim test --encoder FILE` with that "
                            "encoder file")
    actual = file_sha256(file)
    if actual != sha:
        raise ProtocolError(f"{trained}, not on {file} (sha256 {actual[:12]}): give `cosim test --encoder FILE` "
                            f"with the file its run was trained on, or train the run again with --encoder {file}")
    try:
        return _load_encoder(str(file.resolve()), sha)
    except EncoderError as exc:
        raise ProtocolError(f"{trained}: {exc}") from None


def load_for_slot(path: Path, algo: str, image_size: int = 84, encoder: Path | str | None = None):
    """Load the checkpoint given for `algo`'s AC, refusing one that cannot drive it
    (a checkpoint trained on K stacked frames is tested on K, one trained on the nav
    observation with its measurements: :func:`drive`). A checkpoint whose run trained on a
    frozen encoder's features gets that encoder as its ``frame_encoder`` attribute
    (:func:`frame_encoder`; ``encoder``: the file `cosim test --encoder` gives), which
    :func:`drive` encodes its AC's frames with.

    Raises:
        agents.CheckpointError: the file is missing or corrupt.
        ProtocolError: it holds another algorithm, an action space of the other kind
            (a continuous actor in a discrete slot) or another camera size, or its run's
            encoder is missing or not the file given (another hash); the message names the file.
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
    agent.draws_route = draws_route(path)
    agent.frame_encoder = frame_encoder(path, encoder)
    if agent.frame_encoder is not None:
        _check_features(path, agent, agent.frame_encoder)
        return agent
    shape = tuple(image_space(agent.observation_space).shape)
    if obs_of(agent) == "state" and not is_state_space(agent.observation_space):
        raise ProtocolError(
            f"checkpoint {path} sees vectors of shape {shape}, not the state track's ({STATE_DIM},): a run trained "
            "with --encoder (its features) records its encoder in its run folder's config.yaml; test the "
            "checkpoint where its run wrote it")
    if obs_of(agent) != "state" and (len(shape) != 3 or shape[:2] != (image_size, image_size)
                                     or shape[2] % 3 or not shape[2]):
        raise ProtocolError(
            f"checkpoint {path} sees observations of shape {shape}, the test environments give "
            f"{(image_size, image_size, 3)} camera images (or K of them stacked, "
            f"{(image_size, image_size, '3K')}); give a checkpoint trained on them"
        )
    return agent


def _check_features(path: Path, agent, encoder) -> None:
    """Refuse a checkpoint whose observations are not K of ``encoder``'s feature vectors."""
    shape = tuple(getattr(agent.observation_space, "shape", None) or ())
    if len(shape) != 1 or shape[0] % encoder.features_dim or not shape[0]:
        raise ProtocolError(f"checkpoint {path} sees observations of shape {shape}, but its run trained on the "
                            f"{encoder.features_dim} features per frame of the encoder {encoder.path}; give a "
                            "checkpoint of that run")


def frame_stack_of(agent) -> int:
    """Camera frames a checkpoint's agent observes at once: its image channels / 3
    (a run trained with ``frame_stack`` K has 84x84x3K images), its features / the frozen
    encoder's per frame (``--encoder``: 512 K); 1 for the state track."""
    encoder = getattr(agent, "frame_encoder", None)
    if encoder is not None:
        return int(agent.observation_space.shape[0]) // encoder.features_dim
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
    trained on K frames, or inside a :class:`~eval.testing.rollout.EncodedPolicy` with that AC's
    own feature history when it was trained on a frozen encoder's features (``frame_encoder``,
    set by :func:`load_for_slot`); inside a :class:`~eval.testing.rollout.RepeatPolicy` that holds each
    action for the checkpoint's ``action_repeat`` steps when it was trained with one. A
    route-trained agent (``draws_route``, set by :func:`load_for_slot`) turns on the route camera
    of AC ``slot`` in ``env`` (``CosimParallelEnv.draw_routes``; call it before the episode's
    reset), and only of that AC. All read from the checkpoint and its run folder, so ACs of every
    variant share one test environment.

    Raises:
        ProtocolError: a nav-, state- or route-trained agent without the env and slot it drives.
    """
    if getattr(agent, "draws_route", False):
        if env is None or slot is None:
            raise ProtocolError(f"{agent.algo} was trained with --obs route: give drive() the test env and "
                                "the AC slot it drives, to draw that AC's route into its camera")
        env.unwrapped.draw_routes(sorted(env.unwrapped.route_agents | {slot}))
    k = frame_stack_of(agent)
    policy = agent if sample_seed is None else SampledPolicy(agent, sample_seed)
    encoder = getattr(agent, "frame_encoder", None)
    if encoder is not None:  # --encoder: its frames' features, K of them, in place of the frames
        policy = EncodedPolicy(policy, encoder, k)
        return RepeatPolicy(policy, repeat) if (repeat := action_repeat_of(agent)) > 1 else policy
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

