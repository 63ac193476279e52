"""Every algorithm trains on ``Dict(image, measurements)`` observations (cosim's ``--obs nav``):
the buffers keep each transition's measurements with its image, the vector env carries both
through its worker processes, A3C's and IMPALA's unrolls hold them, checkpoints record the Dict
space and an agent refuses the other variant in one line (docs/task.md, "Observation").

The observations come from agents.envs.ScriptedParallelEnv(nav=True): its image and its
measurements both hold (env, agent, step, seed, action), so a part that strayed from its
transition shows.
"""

import functools

import gymnasium as gym
import numpy as np
import pytest
import torch

from agents.a3c import A3CConfig, train_a3c
from agents.base import ObservationError, check_observations
from agents.buffers import ReplayBuffer, RolloutBuffer
from agents.ddpg import DDPGConfig
from agents.dqn import DQNConfig
from agents.envs import ScriptedParallelEnv
from agents.impala import IMPALAConfig, train_impala
from agents.loop import run_loop
from agents.networks import ImageMeasurementsEncoder
from agents.ppo import PPOConfig
from agents.registry import get_agent_class
from agents.td3 import TD3Config
from agents.vector import InProcessVectorEnv, VectorEnv
from cosim.wrappers import FrameHistory

NAV = ScriptedParallelEnv(nav=True).observation_space("agent_0")
IMAGE = NAV["image"]
FAST = {
    "ppo": PPOConfig(rollout_steps=16, batch_size=8, epochs=1),
    "dqn": DQNConfig(learning_starts=8, batch_size=8, buffer_size=64, train_freq=1, target_update_interval=10),
    "ddpg": DDPGConfig(learning_starts=8, batch_size=8, buffer_size=64),
    "td3": TD3Config(learning_starts=8, batch_size=8, buffer_size=64, policy_delay=1),
}


class BoxActions(ScriptedParallelEnv):
    """The scripted nav env with a continuous action (its sign picks the scripted action)."""

    def action_space(self, agent):
        return gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def step(self, actions):
        return super().step({a: int(np.asarray(v)[0] > 0) for a, v in actions.items()})


def _env_fns(algo: str, n: int = 2):
    cls = BoxActions if algo in ("ddpg", "td3") else ScriptedParallelEnv
    return [functools.partial(cls, i, nav=True) for i in range(n)]


def _encoder(agent) -> ImageMeasurementsEncoder:
    """The encoder of the network that learns the features (TD3's actor reads the critic's)."""
    main = {"ppo": "net", "dqn": "q_network", "ddpg": "critic", "td3": "critic"}.get(agent.algo, "actor_critic")
    return next(m for m in agent.networks[main].modules() if isinstance(m, ImageMeasurementsEncoder))


def _nav(values, k: int = 1):
    """A nav observation (k stacked frames) whose image and measurements both hold ``values``."""
    image = np.zeros((36, 36, 3), np.uint8)
    image.reshape(-1)[: len(values)] = np.asarray(values) % 256
    history = FrameHistory(k)
    return history, {"image": history.push(image), "measurements": np.asarray(values, np.float32)}


@pytest.mark.parametrize("k, columns", [(1, 1), (4, 2)])
def test_replay_samples_keep_each_transitions_measurements_with_its_image(k, columns):
    """The image is stored one frame per slot, the measurements beside it: every sampled row's
    measurements are those of the same transition's image, for obs and next_obs, across episode
    ends and the truncated episodes' final observations kept on the side."""
    space = gym.spaces.Dict({"image": gym.spaces.Box(0, 255, (36, 36, 3 * k), np.uint8),
                             "measurements": NAV["measurements"]})
    buf = ReplayBuffer(30 * columns, space, gym.spaces.Discrete(2), seed=0, columns=columns)
    assert buf.obs.shape == (30 * columns, 36, 36, 3) and buf.measurements.shape == (30 * columns, 5)
    step = 0
    for column in range(columns):
        for episode, (length, end) in enumerate([(7, "term"), (5, "trunc"), (40, None)]):
            history, obs = _nav([column, episode, 0, step, k], k)
            for t in range(1, length + 1):
                step += 1
                frame = np.zeros((36, 36, 3), np.uint8)
                frame.reshape(-1)[:5] = np.asarray([column, episode, t, step, k]) % 256
                nxt = {"image": history.push(frame),
                       "measurements": np.asarray([column, episode, t, step, k], np.float32)}
                buf.add(obs, t % 2, float(step), nxt, t == length and end == "term",
                        t == length and end == "trunc", column=column)
                obs = nxt
    sample = buf.sample(500)
    for part in (sample.obs, sample.next_obs):
        assert set(part) == {"image", "measurements"}
        newest = part["image"][:, 0, :2, -3:].reshape(-1, 6)[:, :5].numpy()  # the newest frame's numbers
        np.testing.assert_array_equal(newest, part["measurements"].numpy() % 256)
    # and the row is the transition sampled: its next observation is one step on
    going_on, steps = sample.terminateds.numpy() == 0, sample.rewards.numpy()
    np.testing.assert_array_equal(sample.obs["measurements"][:, 3].numpy() + 1, steps)
    np.testing.assert_array_equal(sample.next_obs["measurements"][going_on, 3].numpy(), steps[going_on])


def test_the_rollout_buffer_stores_and_grows_dict_observations():
    buf = RolloutBuffer(2, NAV, n_logits=3)
    for t in range(3):
        buf.ensure_capacity(t + 1)
        buf.add(_nav([0, 0, t, 0, 0])[1], 0, 0.0, 0.0, 0.0, False, False)
    np.testing.assert_array_equal(buf.obs["measurements"][:, 2], [0, 1, 2])
    np.testing.assert_array_equal(buf.obs["image"][:, 0, 0, 2], [0, 1, 2])


def test_worker_processes_carry_both_parts_like_the_in_process_env():
    fns = _env_fns("ppo")
    with InProcessVectorEnv(fns) as local, VectorEnv(fns) as remote:
        mine, theirs = local.reset(seed=3), remote.reset(seed=3)
        for _ in range(8):  # the arrays of a step are views: compare before the next
            for a in local.possible_agents:
                for kind in ("obs", "next_obs"):
                    for key in ("image", "measurements"):
                        np.testing.assert_array_equal(getattr(mine, kind)[a][key], getattr(theirs, kind)[a][key])
                np.testing.assert_array_equal(mine.obs[a]["image"][:, 0, 0, 2], mine.obs[a]["measurements"][:, 2])
            actions = {a: np.ones(2, np.int64) for a in local.possible_agents}
            mine, theirs = local.step(actions), remote.step(actions)


def _check_trained(agent, initial_mlp: torch.Tensor, tmp_path) -> None:
    """It learned through the measurement MLP; its checkpoint keeps the Dict space; it refuses
    an image alone in one line naming --obs nav."""
    assert not torch.equal(_encoder(agent).mlp[0].weight, initial_mlp), "the measurement MLP learned"
    agent.save(tmp_path / f"{agent.algo}.pt")
    loaded = get_agent_class(agent.algo).load(tmp_path / f"{agent.algo}.pt")
    assert loaded.observation_space == NAV
    obs = ScriptedParallelEnv(nav=True).reset(seed=0)[0]["agent_0"]
    assert np.array_equal(np.asarray(loaded.act(obs, deterministic=True)),
                          np.asarray(agent.act(obs, deterministic=True)))
    with pytest.raises(ObservationError, match=r"trained on nav observations \(36x36x3 image \+ 5 measurements\) "
                       r"but is given image observations \(36x36x3\); use --obs nav") as info:
        loaded.act(obs["image"], deterministic=True)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("algo", ["ppo", "dqn", "ddpg", "td3"])
def test_the_vector_loop_trains_every_sync_algorithm_on_nav_observations(algo, tmp_path):
    cls = get_agent_class(algo)
    fns = _env_fns(algo)
    with InProcessVectorEnv(fns) as venv:
        agents = {a: cls.from_spaces(venv.observation_space(a), venv.action_space(a), FAST[algo], seed=k)
                  for k, a in enumerate(venv.possible_agents)}
        initial = _encoder(agents["agent_0"]).mlp[0].weight.detach().clone()
        stats = run_loop(agents, venv, 40, seed=0)
    assert stats.last_metrics.get("agent_0"), f"{algo} learned"
    _check_trained(agents["agent_0"], initial, tmp_path)


@pytest.mark.parametrize("train, config", [(train_a3c, A3CConfig(n_steps=5)),
                                           (train_impala, IMPALAConfig(unroll_length=5, batch_size=2))])
def test_a3c_and_impala_learn_from_nav_unrolls_on_env_processes(train, config, tmp_path):
    env = ScriptedParallelEnv(nav=True)
    trained = train(_env_fns("a3c"), NAV, env.action_space("agent_0"), env.possible_agents, config,
                    total_steps=30, seed=0)
    fresh = get_agent_class(trained["agent_0"].algo).from_spaces(NAV, env.action_space("agent_0"), config, seed=0)
    assert trained["agent_0"].num_updates > 0
    _check_trained(trained["agent_0"], _encoder(fresh).mlp[0].weight, tmp_path)


@pytest.mark.parametrize("algo", ["ppo", "a3c", "impala", "dqn", "ddpg", "td3"])
def test_an_image_agent_refuses_nav_observations_and_spaces_of_the_other_variant(algo):
    actions = gym.spaces.Box(-1.0, 1.0, (2,), np.float32) if algo in ("ddpg", "td3") else gym.spaces.Discrete(3)
    agent = get_agent_class(algo).from_spaces(IMAGE, actions)
    obs = ScriptedParallelEnv(nav=True).reset(seed=0)[0]["agent_0"]
    with pytest.raises(ObservationError, match=r"trained on image observations \(36x36x3\) but is given nav "
                       r"observations \(36x36x3 image \+ 5 measurements\); use --obs image"):
        agent.act(obs, deterministic=True)
    with pytest.raises(ObservationError, match="use --obs nav"):
        check_observations(NAV, IMAGE, "checkpoint x.pt")
    stacked = gym.spaces.Dict({"image": gym.spaces.Box(0, 255, (36, 36, 6), np.uint8),
                               "measurements": NAV["measurements"]})
    with pytest.raises(ObservationError, match=r"trained on 2 stacked camera frame\(s\).*use --frame-stack 2"):
        check_observations(stacked, NAV, "checkpoint x.pt")
    check_observations(NAV, NAV, "checkpoint x.pt")
