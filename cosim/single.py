"""Single-agent Gymnasium view of the driving environment: one AC, same semantics.

``background=False, pedestrians=False`` gives the empty world of the paper's
single-agent test scenario (SPEC §6, Scenario 2).
"""

from __future__ import annotations

import gymnasium as gym

from cosim.env import CosimParallelEnv, _check_seed
from cosim.scenario import Scenario
from cosim.version import TASK_VERSION

GYM_IDS = {
    f"cosim/{name}-v{TASK_VERSION}": env
    for name, env in (("Straight", "env_1"), ("ThreeWay", "env_2"), ("FourWay", "env_3"),
                      ("Roundabout", "env_4"), ("Merge", "env_5"))
}
"""Gymnasium id -> scenario; the ids' suffix is the task version (cosim.TASK_VERSION)."""


class SingleAgentEnv(gym.Env):
    """One learning car (``ac_0``) of a :class:`~cosim.env.CosimParallelEnv`.

    ``frame_stack`` K > 1 observes the last K camera frames, as ``cosim train`` does by
    default (K = 4; docs/task.md, "Observation"); 1 (the default here) the camera itself.
    ``obs="nav"``: a Dict of those frames and the measurements vector
    (cosim.wrappers.NavObservation); ``obs="state"``: the state track, a 65-number vector with
    the camera off (cosim.state; frame_stack 1); ``obs="route"``: the frames with the AC's route
    ahead drawn in (the route camera).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, scenario: str | Scenario = "env_1", action_type: str = "discrete",
                 render_mode: str | None = None, frame_stack: int = 1, obs: str = "image", **kwargs):
        from cosim.wrappers import (
            check_frame_stack,
            check_obs_variant,
            check_state_stack,
            observation_wrappers,
        )

        check_frame_stack(frame_stack)
        check_obs_variant(obs)
        check_state_stack(obs, frame_stack)
        if obs == "state":
            kwargs.setdefault("camera", False)
        self._env = observation_wrappers(CosimParallelEnv(
            scenario, num_agents=1, action_types=action_type, render_mode=render_mode, **kwargs
        ), frame_stack=frame_stack, obs=obs)
        self.agent = self._env.possible_agents[0]
        self.observation_space = self._env.observation_space(self.agent)
        self.action_space = self._env.action_space(self.agent)
        self.render_mode = render_mode

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        _check_seed(seed, "reset(seed=...)")  # before Gymnasium's own, which names no call
        super().reset(seed=seed)
        obs, infos = self._env.reset(seed=seed, options=options)
        return obs[self.agent], infos[self.agent]

    def step(self, action):
        obs, rew, term, trunc, info = self._env.step({self.agent: action})
        a = self.agent
        return obs[a], rew[a], term[a], trunc[a], info[a]

    def render(self):
        return self._env.render()

    def close(self) -> None:
        self._env.close()

    @property
    def parallel(self):
        """The multi-agent env underneath (with its observation wrappers, if any)."""
        return self._env


def single_env(scenario: str | Scenario = "env_1", **kwargs) -> SingleAgentEnv:
    """One AC in a driving environment, as a Gymnasium Env."""
    return SingleAgentEnv(scenario, **kwargs)


def register_envs() -> None:
    """Register the five environments with Gymnasium (``gym.make("cosim/FourWay-v5")``)."""
    for env_id, name in GYM_IDS.items():
        if env_id not in gym.registry:
            gym.register(env_id, entry_point="cosim.single:SingleAgentEnv",
                         kwargs={"scenario": name})
