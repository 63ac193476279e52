"""`cosim test` turns the test env's cameras off when no AC of it reads an image (state-track
ACs, the autopilot, random: eval/testing/rollout.py ``use_cameras``): no PyBullet mirror is
built and the records are those of the same test with the cameras on."""

import numpy as np
import pandas as pd
import pytest
from gymnasium import spaces

from agents.registry import get_agent_class
from cosim.state import state_space
from eval.testing import jobs
from eval.testing.checkpoints import find_checkpoints
from eval.testing.jobs import run_protocol
from eval.testing.policies import policy_factory
from eval.testing.protocol import ProtocolPlan

ALGOS = ["ppo", "td3"]  # a sampled discrete policy and a greedy continuous one
PLAN = ProtocolPlan(envs=("env_2",), scenarios=(1, 2), episodes=1, steps=6, agents=2)


def _state_runs(runs):
    for algo in ALGOS:
        ckpt = runs / f"env_2__{algo}__0__20260101-000000" / "checkpoints" / "ac_0"
        ckpt.mkdir(parents=True)
        act = spaces.Box(-1.0, 1.0, (2,), np.float32) if algo == "td3" else spaces.Discrete(9)
        get_agent_class(algo).from_spaces(state_space(), act).save(ckpt / "latest.pt")
    return find_checkpoints(runs, ALGOS)


def _no_mirror(monkeypatch):
    import cosim.mirror

    def no_mirror(*args, **kwargs):
        raise AssertionError("a test whose ACs read no image must not build the PyBullet mirror")

    monkeypatch.setattr(cosim.mirror.Mirror, "__init__", no_mirror)


@pytest.mark.parametrize("kind", ["trained", "autopilot"])
def test_a_test_without_image_acs_builds_no_mirror_and_records_what_the_camera_env_does(tmp_path, monkeypatch, kind):
    ckpts = _state_runs(tmp_path / "runs") if kind == "trained" else None
    with monkeypatch.context() as m:  # the cameras on, as before: the reference records
        m.setattr(jobs, "use_cameras", lambda env, policies: True)
        with_cameras = run_protocol(PLAN, policy_factory(kind, ckpts), ALGOS)
    _no_mirror(monkeypatch)
    without = run_protocol(PLAN, policy_factory(kind, ckpts), ALGOS)
    assert len(without) == 6 * (2 + 2) and set(without.scenario) == {1, 2}
    pd.testing.assert_frame_equal(without, with_cameras)


def test_an_image_ac_keeps_the_cameras_and_wrappers_say_what_they_wrap():
    import cosim
    from eval.testing.robustness import Perturbed
    from eval.testing.rollout import (
        AutopilotPolicy,
        NavPolicy,
        RandomPolicy,
        RepeatPolicy,
        SampledPolicy,
        StackedPolicy,
        StatePolicy,
        needs_camera,
        use_cameras,
    )

    env = cosim.parallel_env("env_1", num_agents=2, horizon=5, seed=0, image_size=16)
    try:
        class Agent:  # a trained agent: it reads the observation it is given (no observes_camera)
            algo, generator, device = "dqn", None, "cpu"

            def act(self, obs, deterministic=True):
                return 4

        agent = Agent()
        state = StatePolicy(agent, env, "ac_0")
        auto, rand = AutopilotPolicy(env, "ac_1"), RandomPolicy(env.action_space("ac_1"))
        assert not any(needs_camera(p) for p in (state, auto, rand, RepeatPolicy(state, 2),
                                                 Perturbed(state, None, "dropout", 0.5, 0)))
        assert all(needs_camera(p) for p in (agent, SampledPolicy(agent, 0), NavPolicy(agent, env, "ac_0"),
                                             StackedPolicy(agent, 2), RepeatPolicy(agent, 2)))
        assert use_cameras(env, {"ac_0": agent, "ac_1": auto}) and env.unwrapped.camera
        assert env.reset(seed=0)[0]["ac_0"].shape == (16, 16, 3)
    finally:
        env.close()
