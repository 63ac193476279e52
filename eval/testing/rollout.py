"""Run policies in an environment for fixed-seed episodes and collect per-step records.

A policy is anything with ``act(obs, deterministic=True)`` (every trained agent)
or a callable ``policy(obs) -> action``. :class:`RandomPolicy` and
:class:`AutopilotPolicy` are the two references; :class:`StackedPolicy` feeds a
policy trained on stacked frames its own frame history, :class:`EncodedPolicy` one trained on
a frozen encoder's features its own features, :class:`NavPolicy` one trained on
the ``nav`` observation its own measurements, :class:`StatePolicy` one trained on the state
track its own state vector, :class:`RepeatPolicy` holds the actions of one
trained with an action repeat. :func:`use_cameras` turns a test env's cameras off when no
policy driving it reads an image (:func:`needs_camera`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from cosim.controller import Autopilot
from eval.testing.records import record_row, to_frame


class RandomPolicy:
    """Uniform random actions from the agent's action space (seeded)."""

    name = "random"
    observes_camera = False

    def __init__(self, space, seed: int = 0):
        self.space = space
        self.space.seed(seed)

    def act(self, obs, deterministic: bool = True):
        return self.space.sample()


class AutopilotPolicy:
    """The scripted lane follower as a policy of one AC of a cosim env (privileged)."""

    name = "autopilot"
    observes_camera = False

    def __init__(self, env, agent: str):
        self.env = env
        self.agent = agent
        self.discrete = env.action_types[agent] == "discrete"
        self._pilot = None

    def act(self, obs, deterministic: bool = True):
        world = self.env.world
        if self._pilot is None or self._pilot.world is not world:
            self._pilot = Autopilot(world, self.agent)
        return self._pilot.act_discrete() if self.discrete else self._pilot.act()

    def reset(self) -> None:
        self._pilot = None


class StackedPolicy:
    """A policy trained on ``k`` stacked camera frames, driving one AC of a test env.

    It keeps that AC's frame history itself (cosim.wrappers.FrameHistory, the stacking the
    training env's FrameStack does), so ACs of runs with different ``k`` share one test
    environment; ``reset()`` (called by :func:`run_episodes` at every episode start)
    clears it, and the first frame of an episode fills all ``k`` slots, as in training.
    """

    def __init__(self, policy, k: int):
        from cosim.wrappers import FrameHistory

        self.policy, self.history = policy, FrameHistory(k)
        self.algo = getattr(policy, "algo", None)
        self.name = getattr(policy, "name", None) or type(policy).__name__

    @property
    def frame_stack(self) -> int:
        return self.history.k

    @property
    def observes_camera(self) -> bool:
        return needs_camera(self.policy)

    def reset(self) -> None:
        self.history.clear()
        if hasattr(self.policy, "reset"):
            self.policy.reset()

    def act(self, obs, deterministic: bool = True):
        return _act(self.policy, self.history.push(obs))


class EncodedPolicy:
    """A policy trained on a frozen encoder's features (`cosim train --encoder`,
    eval.training.encoder.observation), driving one AC of a test env that gives camera frames:
    it encodes each frame of its AC (agents.encoder.FrozenEncoder, the same features as the
    training env's batch gave: fixed-size chunks) and keeps that AC's last ``k`` feature
    vectors (cosim.wrappers.FrameHistory, oldest first, cleared at ``reset()``), as the
    training env's FrameStack over the features did.
    """

    def __init__(self, policy, encoder, k: int):
        from cosim.wrappers import FrameHistory

        self.policy, self.encoder, self.history = policy, encoder, FrameHistory(k)
        self.algo = getattr(policy, "algo", None)
        self.name = getattr(policy, "name", None) or type(policy).__name__

    @property
    def frame_stack(self) -> int:
        return self.history.k

    def reset(self) -> None:
        self.history.clear()
        if hasattr(self.policy, "reset"):
            self.policy.reset()

    def act(self, obs, deterministic: bool = True):
        return _act(self.policy, self.history.push(self.encoder.encode(obs)))


class RepeatPolicy:
    """A policy trained with ``action_repeat`` k (cosim.wrappers.ActionRepeat), driving one AC
    of a test env that asks for an action every step: it decides at the episode's steps 0, k,
    2k, ... and repeats that action in between, so the policies inside it (a
    :class:`StackedPolicy`'s frame history, a :class:`NavPolicy`'s measurements) see only the
    steps it decides on, as in training. ``reset()`` starts the count again.
    """

    def __init__(self, policy, k: int):
        from cosim.wrappers import check_action_repeat

        self.policy, self.k = policy, check_action_repeat(k)
        self.count, self.action = 0, None
        self.algo = getattr(policy, "algo", None)
        self.name = getattr(policy, "name", None) or type(policy).__name__

    @property
    def observes_camera(self) -> bool:
        return needs_camera(self.policy)

    def reset(self) -> None:
        self.count, self.action = 0, None
        if hasattr(self.policy, "reset"):
            self.policy.reset()

    def act(self, obs, deterministic: bool = True):
        if self.count % self.k == 0:
            self.action = _act(self.policy, obs)
        self.count += 1
        return self.action


class NavPolicy:
    """A policy trained on the ``nav`` observation (cosim.wrappers.NavObservation), driving AC
    ``agent`` of a test env that gives camera images only.

    It builds that AC's measurements itself, as the training env's NavObservation does: from
    the AC's route (cosim.wrappers.RouteGuide, read again after every ``reset()``) and the
    speed and distance to the goal in the env's infos of the step that gave the image
    (``CosimParallelEnv.last_infos``). So ACs trained on either observation share one test
    environment. Inside a :class:`StackedPolicy` it gets the stacked frames as its image.
    """

    def __init__(self, policy, env, agent: str):
        self.policy, self.env, self.agent = policy, env, agent
        self.guide = None
        self.algo = getattr(policy, "algo", None)
        self.name = getattr(policy, "name", None) or type(policy).__name__

    def reset(self) -> None:
        self.guide = None
        if hasattr(self.policy, "reset"):
            self.policy.reset()

    def act(self, obs, deterministic: bool = True):
        from cosim.wrappers import RouteGuide

        if self.guide is None:
            self.guide = RouteGuide.of_agent(self.env, self.agent)
        return _act(self.policy, self.guide.observe(obs, self.env.unwrapped.last_infos[self.agent]))


class StatePolicy:
    """A policy trained on the state track (``--obs state``, cosim.state), driving AC ``agent``
    of a test env that may give camera images (ACs of other runs share it): it ignores the
    env's observation and builds that AC's state vector itself from the env's world and last
    controls (cosim.state.agent_state), as the training env with its cameras off does.
    """

    observes_camera = False

    def __init__(self, policy, env, agent: str):
        self.policy, self.env, self.agent = policy, env, agent
        self.algo = getattr(policy, "algo", None)
        self.name = getattr(policy, "name", None) or type(policy).__name__

    def reset(self) -> None:
        if hasattr(self.policy, "reset"):
            self.policy.reset()

    def act(self, obs, deterministic: bool = True):
        from cosim.state import agent_state

        return _act(self.policy, agent_state(self.env, self.agent))


class SampledPolicy:
    """A stochastic-policy agent (PPO, A3C, IMPALA) tested by sampling its action
    distribution, the policy its training optimised, instead of taking the mode.

    Draws come from this wrapper's own torch generator, seeded with ``seed`` and the
    episode count at every ``reset()``: the same test gives the same draws, and two
    slots driven by one checkpoint do not share a stream.
    """

    def __init__(self, agent, seed: int):
        import torch

        self.agent, self.seed, self.episodes = agent, int(seed), 0
        self.algo = getattr(agent, "algo", None)
        self.generator = torch.Generator(device=getattr(agent, "device", "cpu"))
        self.generator.manual_seed(self.seed)

    def reset(self) -> None:
        self.generator.manual_seed(self.seed * 100_003 + self.episodes)
        self.episodes += 1

    def act(self, obs, deterministic: bool = True):
        own, self.agent.generator = self.agent.generator, self.generator
        try:
            return self.agent.act(obs, deterministic=False)
        finally:
            self.agent.generator = own


def needs_camera(policy) -> bool:
    """Whether ``policy`` reads the camera image its AC observes: False for the references
    (:class:`RandomPolicy`, :class:`AutopilotPolicy`) and a :class:`StatePolicy`, and for a
    wrapper (``observes_camera`` a property) around one of them; True for anything else (a
    trained agent, a :class:`NavPolicy`, a policy that does not say)."""
    return bool(getattr(policy, "observes_camera", True))


def use_cameras(env, policies: Mapping[str, object]) -> bool:
    """Keep ``env``'s cameras (a ``CosimParallelEnv``, before its first reset) only if one of
    ``policies`` reads an image (:func:`needs_camera`); else turn them off
    (``CosimParallelEnv.cameras_off``: no PyBullet mirror is built, each AC observes its state
    vector, which none of these policies reads). The world, hence every record, is the same
    either way; a state-only or reference-only test runs several times faster. Returns whether
    the cameras stay on."""
    if any(needs_camera(p) for p in policies.values()):
        return True
    env.cameras_off()
    return False


def _act(policy, obs):
    if hasattr(policy, "act"):
        return policy.act(obs, deterministic=True)
    return policy(obs)


def run_episodes(env, policies: Mapping[str, object], seeds: Sequence[int],
                 algorithms: Mapping[str, str] | None = None, progress=None) -> pd.DataFrame:
    """Run one episode per seed with the given policies; return the per-step records.

    Args:
        env: a cosim ParallelEnv (its agents must all have policies).
        policies: agent id -> policy.
        seeds: one episode per seed (fixed seeds make evaluations comparable).
        algorithms: agent id -> algorithm name for the records (default: policy.algo/name).
        progress: optional callable(episode_index) for progress bars.
    """
    missing = [a for a in env.possible_agents if a not in policies]
    if missing:
        raise ValueError(f"no policy for agent(s) {missing}")
    names = dict(algorithms or {})
    for a, p in policies.items():
        names.setdefault(a, getattr(p, "algo", None) or getattr(p, "name", type(p).__name__))
    rows: list[dict] = []
    for episode, seed in enumerate(seeds):
        obs, infos = env.reset(seed=int(seed))
        for p in policies.values():
            if hasattr(p, "reset"):
                p.reset()
        step = 0
        while env.agents:
            actions = {a: _act(policies[a], obs[a]) for a in env.agents}
            obs, rewards, terms, truncs, infos = env.step(actions)
            step += 1
            for a in rewards:
                rows.append(record_row(
                    episode=episode, seed=int(seed), step=step, agent=a, algorithm=names[a],
                    info=infos[a], reward=rewards[a], terminated=terms[a], truncated=truncs[a],
                ))
        if progress is not None:
            progress(episode)
    return to_frame(rows)


def mean_return(records: pd.DataFrame) -> float:
    """Mean over (episode, agent) of the undiscounted return."""
    if records.empty:
        return float("nan")
    return float(records.groupby(["episode", "agent"])["reward"].sum().mean())


__all__ = ["AutopilotPolicy", "EncodedPolicy", "NavPolicy", "RandomPolicy", "RepeatPolicy", "StackedPolicy", "StatePolicy", "mean_return",
           "needs_camera", "run_episodes", "use_cameras", "np"]
