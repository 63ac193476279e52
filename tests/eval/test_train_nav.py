"""`cosim train --obs nav`: recorded in the run's config, trained by every algorithm (single env,
--envs N, A3C/IMPALA), refused on a resume whose config.yaml was edited to the other variant,
and tested beside image-trained ACs: `cosim test` builds a nav AC's measurements in the shared
test env from its checkpoint (docs/task.md, "Observation")."""

import numpy as np
import pytest
import yaml
from gymnasium import spaces

import agents
from agents.base import ObservationError
from agents.networks import ImageMeasurementsEncoder
from agents.registry import POLICY_NETWORKS, get_agent_class
from eval.cli import main
from eval.training.train import TrainError, make_config, train

IMAGE = spaces.Box(0, 255, (84, 84, 12), np.uint8)  # the smoke preset's 4-frame stack


def _nav_space(image=IMAGE):
    from cosim.wrappers import nav_space

    return spaces.Dict({"image": image, "measurements": nav_space()})


def _has_measurement_mlp(agent) -> bool:
    """The networks that read the observation (DDPG's and TD3's actor reads the critic's
    features) have the CNN and the measurement MLP."""
    readers = ("critic",) if agent.algo in ("ddpg", "td3") else POLICY_NETWORKS[agent.algo]
    return all(any(isinstance(m, ImageMeasurementsEncoder) for m in agent.networks[name].modules())
               for name in readers)


def test_obs_is_part_of_the_config_and_a_bad_value_is_refused(tmp_path):
    from eval.training.runfolder import load_run_config
    from eval.training.train import make_env

    assert make_config("ppo", "env_1", "smoke").obs == "image"  # the paper's observation
    cfg = make_config("td3", "env_1", "smoke", obs="nav")
    assert cfg.to_dict()["obs"] == "nav"
    with pytest.raises(TrainError, match="--obs must be image or nav or state or route, got 'rgb'"):
        make_config("ppo", "env_1", "smoke", obs="rgb")
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict()))
    assert load_run_config(tmp_path).obs == "nav"
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({**cfg.to_dict(), "obs": "rgb"}))
    with pytest.raises(TrainError, match="config.yaml: 'obs' must be image or nav or state or route, got 'rgb'"):
        load_run_config(tmp_path)
    older = {k: v for k, v in cfg.to_dict().items() if k != "obs"}  # written before the option
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(older))
    assert load_run_config(tmp_path).obs == "image"
    env = make_env(cfg.to_dict())
    try:
        assert env.observation_space("ac_0") == _nav_space()
    finally:
        env.close()


def test_cosim_train_obs_nav_writes_checkpoints_with_the_measurement_mlp_that_drive_beside_image_acs(tmp_path):
    from eval.testing.checkpoints import find_checkpoints
    from eval.testing.jobs import run_protocol
    from eval.testing.policies import policy_factory
    from eval.testing.protocol import ProtocolPlan

    runs = tmp_path / "runs"
    assert main(["train", "--algo", "dqn", "--preset", "smoke", "--agents", "1", "--steps", "4",
                 "--obs", "nav", "--out", str(runs), "--quiet"]) == 0
    (run,) = runs.iterdir()
    assert yaml.safe_load((run / "config.yaml").read_text())["obs"] == "nav"
    agent = agents.load(run / "checkpoints" / "ac_0" / "best.pt")  # validated on nav episodes too
    assert agent.observation_space == _nav_space() and _has_measurement_mlp(agent)
    with pytest.raises(ObservationError, match=r"trained on nav observations \(84x84x12 image \+ 7 "
                       r"measurements\) but is given image observations \(84x84x12\); use --obs nav"):
        agent.act(np.zeros((84, 84, 12), np.uint8), deterministic=True)
    image = runs / "env_1__ppo__0__20260101-000000" / "checkpoints" / "ac_0"
    image.mkdir(parents=True)
    get_agent_class("ppo").from_spaces(IMAGE, spaces.Discrete(9)).save(image / "latest.pt")
    make = policy_factory("trained", find_checkpoints(runs, ["ppo", "dqn"]))
    plan = ProtocolPlan(envs=("env_1",), scenarios=(1,), episodes=1, steps=3, agents=2)
    records = run_protocol(plan, make, ["ppo", "dqn"])  # one env: an image AC and a nav AC
    assert sorted(records.algorithm.unique()) == ["dqn", "ppo"] and len(records) == 2 * 3


def test_a_resume_with_the_other_obs_than_the_checkpoints_is_refused_in_one_line(tmp_path):
    from eval.training.trainer import _load_or_build

    cfg = make_config("ppo", "env_1", "smoke", agents=1, obs="nav")
    latest = tmp_path / "checkpoints" / "ac_0" / "latest.pt"
    latest.parent.mkdir(parents=True)
    get_agent_class("ppo").from_spaces(_nav_space(), spaces.Discrete(9)).save(latest)
    with pytest.raises(TrainError, match=rf"checkpoint {latest} was trained on nav observations \(84x84x12 "
                       r"image \+ 7 measurements\) but is given image observations \(84x84x12\); use "
                       r"--obs nav \(the run's obs\) with it") as info:
        _load_or_build(cfg, tmp_path, True, IMAGE, spaces.Discrete(9))
    assert "\n" not in str(info.value)
    assert _load_or_build(cfg, tmp_path, True, _nav_space(), spaces.Discrete(9))["ac_0"].observation_space == _nav_space()


class _Spy:
    """A nav-trained checkpoint's agent that records what it is given."""

    algo = "dqn"

    def __init__(self, space):
        self.observation_space, self.seen = space, []

    def act(self, obs, deterministic=True):
        self.seen.append({k: np.array(v, copy=True) for k, v in obs.items()})
        return 1  # forward: the speed measurement moves


def test_the_test_env_gives_a_nav_ac_exactly_its_training_observation():
    """`cosim test` drives every AC in one env that gives camera frames; a nav AC's policy
    (eval.testing.loading.drive: StackedPolicy around NavPolicy) builds, from each frame and the
    env's infos, what the training env's wrappers (FrameStack + NavObservation) give, episode
    after episode."""
    from cosim.env import CosimParallelEnv
    from cosim.wrappers import observation_wrappers
    from eval.testing.loading import drive
    from eval.testing.protocol import ProtocolError

    raw = CosimParallelEnv("env_1", num_agents=2, action_types="discrete", horizon=12, seed=0)
    wrapped = observation_wrappers(raw, frame_stack=2, obs="nav")  # what a --frame-stack 2 --obs nav run trains on
    spies = {a: _Spy(wrapped.observation_space(a)) for a in raw.possible_agents}
    policies = {a: drive(spies[a], env=raw, slot=a) for a in raw.possible_agents}
    with pytest.raises(ProtocolError, match="trained with --obs nav: give drive"):
        drive(spies["ac_0"])
    try:
        for seed in (0, 1):
            obs, _ = wrapped.reset(seed=seed)
            for policy in policies.values():
                policy.reset()
            while wrapped.agents:
                actions = {a: policies[a].act(obs[a]["image"][..., -3:]) for a in wrapped.agents}  # the frame
                for a in actions:
                    for key in ("image", "measurements"):
                        np.testing.assert_array_equal(spies[a].seen[-1][key], obs[a][key])
                obs, *_ = wrapped.step(actions)
    finally:
        wrapped.close()
    seen = np.array([s["measurements"] for s in spies["ac_0"].seen])
    assert len(seen) == 24 and seen[:, 0].max() > 0 and seen[:, 6].min() < 1  # it drove on its route


def _interrupt_at_first_checkpoint(run, step, score):
    raise KeyboardInterrupt


@pytest.mark.slow
@pytest.mark.parametrize("algo, envs", [("ppo", 1), ("ppo", 2), ("a3c", 1), ("impala", 2),
                                        ("dqn", 1), ("ddpg", 1), ("td3", 1)])
def test_every_algorithm_trains_resumes_and_is_tested_on_nav_beside_an_image_ac(tmp_path, algo, envs):
    from eval.testing.checkpoints import find_checkpoints
    from eval.testing.jobs import run_protocol
    from eval.testing.policies import policy_factory
    from eval.testing.protocol import ProtocolPlan
    from eval.testing.rollout import NavPolicy, StackedPolicy

    runs = tmp_path / "runs"
    cfg = make_config(algo, "env_1", "smoke", steps=80, obs="nav", envs=envs)
    with pytest.raises(KeyboardInterrupt):  # stopped after its first checkpoint (40 steps)
        train(cfg, runs, quiet=True, progress=False, keep="all", on_checkpoint=_interrupt_at_first_checkpoint)
    (run,) = runs.iterdir()
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["obs"] == "nav"
    (run / "config.yaml").write_text(yaml.safe_dump({**config, "obs": "image"}))
    with pytest.raises(TrainError, match=r"trained on nav observations .* use --obs nav"):
        train(None, resume=run, progress=False)
    (run / "config.yaml").write_text(yaml.safe_dump(config))
    assert main(["train", "--resume", str(run), "--quiet", "--keep", "all"]) == 0
    assert yaml.safe_load((run / "state.json").read_text())["env_steps"] == 80
    for ac in ("ac_0", "ac_1"):
        for name in ("latest.pt", "best.pt"):
            agent = agents.load(run / "checkpoints" / ac / name)
            assert agent.observation_space == _nav_space() and _has_measurement_mlp(agent)

    other = "ppo" if algo == "dqn" else "dqn"  # an image-trained AC beside it
    image_run = runs / f"env_1__{other}__0__20260101-000000" / "checkpoints" / "ac_0"
    image_run.mkdir(parents=True)
    get_agent_class(other).from_spaces(IMAGE, spaces.Discrete(9)).save(image_run / "latest.pt")
    make = policy_factory("trained", find_checkpoints(runs, [algo, other]))
    nav, image = make(object(), "ac_0", algo), make(object(), "ac_1", other)  # each from its checkpoint
    assert isinstance(nav, StackedPolicy) and isinstance(nav.policy, NavPolicy)
    assert isinstance(image, StackedPolicy) and not isinstance(image.policy, NavPolicy)
    plan = ProtocolPlan(envs=("env_1",), scenarios=(1, 2), episodes=2, steps=5, agents=2)
    records = run_protocol(plan, make, [algo, other])
    assert sorted(records.algorithm.unique()) == sorted([algo, other])
    assert len(records) == 2 * 2 * 5 + 2 * 2 * 5  # scenario 1: 2 ACs, 2 episodes; scenario 2: each alone
