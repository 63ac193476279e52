"""`cosim train --obs state` (the state track, cosim/state.py): every algorithm trains on the
65-number vector with its cameras off and MLPs of the preset's state_hidden, the run records
it, `cosim benchmark --obs state` plans it, and `cosim test` drives a state-trained AC beside
an image-trained one in one shared test env (docs/task.md, "The state track")."""

import numpy as np
import pytest
import yaml
from gymnasium import spaces

import agents
from agents.base import ObservationError
from agents.registry import ALGORITHMS, get_agent_class
from cosim.state import STATE_DIM, state_space
from eval.cli import main

IMAGE = spaces.Box(0, 255, (84, 84, 12), np.uint8)  # the smoke preset's 4-frame stack


@pytest.mark.parametrize("algo", ALGORITHMS)
def test_cosim_train_obs_state_trains_every_algorithm_on_the_state_vector(tmp_path, algo):
    runs = tmp_path / "runs"
    assert main(["train", "--algo", algo, "--preset", "smoke", "--env", "env_2", "--agents", "1",
                 "--steps", "60", "--obs", "state", "--out", str(runs), "--quiet"]) == 0
    (run,) = runs.iterdir()
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["obs"] == "state" and config["frame_stack"] == 1
    agent = agents.load(run / "checkpoints" / "ac_0" / "best.pt")
    assert agent.observation_space == state_space() and tuple(agent.config.hidden) == (256, 256)
    action = agent.act(np.zeros(STATE_DIM, np.float32), deterministic=True)
    assert agent.action_space.contains(np.asarray(action, dtype=agent.action_space.dtype)
                                       if algo in ("ddpg", "td3") else int(action))
    with pytest.raises(ObservationError, match=r"trained on state observations \(65\) but is given image "
                       r"observations \(84x84x12\); use --obs state"):
        agent.act(np.zeros((84, 84, 12), np.uint8), deterministic=True)


def test_cosim_benchmark_obs_state_plans_one_vector_per_trial():
    from eval.scale.benchmark import BenchmarkPlan

    plan = BenchmarkPlan(preset="standard", envs=("env_2",), algos=("dqn", "ppo"), obs="state")
    assert {(c.obs, c.frame_stack, c.agent_config.hidden) for c in plan.cells()} == {("state", 1, (256, 256))}
    assert plan.to_dict()["obs"] == "state"


def test_cosim_test_drives_a_state_ac_beside_an_image_ac_in_one_env(tmp_path):
    from eval.testing.checkpoints import find_checkpoints
    from eval.testing.jobs import run_protocol
    from eval.testing.policies import policy_factory
    from eval.testing.protocol import ProtocolPlan

    runs = tmp_path / "runs"
    assert main(["train", "--algo", "dqn", "--preset", "smoke", "--agents", "1", "--steps", "4",
                 "--obs", "state", "--out", str(runs), "--quiet"]) == 0
    image = runs / "env_1__ppo__0__20260101-000000" / "checkpoints" / "ac_0"
    image.mkdir(parents=True)
    get_agent_class("ppo").from_spaces(IMAGE, spaces.Discrete(9)).save(image / "latest.pt")
    make = policy_factory("trained", find_checkpoints(runs, ["ppo", "dqn"]))
    plan = ProtocolPlan(envs=("env_1",), scenarios=(1,), episodes=1, steps=3, agents=2)
    records = run_protocol(plan, make, ["ppo", "dqn"])  # one env: an image AC and a state AC
    assert sorted(records.algorithm.unique()) == ["dqn", "ppo"] and len(records) == 2 * 3


def test_the_state_track_takes_its_own_update_to_data_ratio_from_the_preset():
    """dqn.yaml's standard ``state_hyperparameters: {train_freq: 2}`` applies with --obs state
    only; the camera keeps the preset's 8, and --set still has the last word."""
    from eval.training.train import make_config

    assert make_config("dqn", "env_2", "standard", obs="state").agent_config.train_freq == 2
    assert make_config("dqn", "env_2", "standard").agent_config.train_freq == 8
    assert make_config("dqn", "env_2", "standard", obs="state",
                       hyper={"train_freq": "4"}).agent_config.train_freq == 4
    assert make_config("dqn", "env_2", "quick", obs="state").agent_config.train_freq == 4  # no entry
