"""The frozen perception encoder (agents/encoder.py): the same frame gives the same features bit
for bit whatever it is encoded with, the file round-trips by its hash, the wrappers encode every
step's frames in one forward pass, and DQN and TD3 learn heads on the features with their own,
unchanged code (MLPs, replay of float features) while the encoder stays as it was."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from agents.configs import DQNConfig, TD3Config
from agents.dqn import DQN
from agents.encoder import (
    CHUNK,
    EncodedGymObservation,
    EncodedObservation,
    EncoderError,
    EncoderNet,
    FrozenEncoder,
    file_sha256,
    load_encoder,
    save_encoder,
)
from agents.envs import ColourBar, MultiColourBar
from agents.loop import run_loop
from agents.networks import MLPEncoder, NatureCNN
from agents.td3 import TD3


def _frames(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, 84, 84, 3), dtype=np.uint8)


@pytest.fixture(scope="module")
def encoder_file(tmp_path_factory):
    torch.manual_seed(0)
    net = EncoderNet((84, 84, 3), 5)
    path = tmp_path_factory.mktemp("encoder") / "enc.pt"
    sha = save_encoder(path, net, labels=list("abcde"), mean=np.zeros(5), std=np.ones(5), info={"frames": 0})
    return path, sha


def test_the_same_frame_gives_the_same_features_bit_for_bit_alone_or_among_others(encoder_file):
    encoder = load_encoder(encoder_file[0])
    frames = _frames(CHUNK + 3)
    alone = np.stack([encoder.encode(f) for f in frames])  # one frame at a time (a test's AC)
    together = encoder.encode(frames)  # a step's ACs at once, over two chunks
    shuffled = encoder.encode(frames[::-1])[::-1]
    assert alone.dtype == np.float32 and alone.shape == (CHUNK + 3, 512)
    assert np.array_equal(alone, together) and np.array_equal(together, shuffled)
    assert np.array_equal(encoder.encode(frames), together)  # and again
    assert not np.array_equal(together[0], together[1])


def test_the_file_is_known_by_its_hash_and_reloads_the_same_features(encoder_file, tmp_path):
    path, sha = encoder_file
    assert sha == file_sha256(path)
    first, again = load_encoder(path), load_encoder(path, expected_sha256=sha)
    assert again.sha256 == sha and again.labels == tuple("abcde") and again.info == {"frames": 0}
    assert np.array_equal(first.encode(_frames(2)), again.encode(_frames(2)))
    assert not any(p.requires_grad for p in again.net.parameters())
    with pytest.raises(EncoderError, match=r"not the 000000000000\.\.\. it was recorded with"):
        load_encoder(path, expected_sha256="0" * 64)
    (tmp_path / "other.pt").write_bytes(b"not torch")
    with pytest.raises(EncoderError, match="not readable"):
        load_encoder(tmp_path / "other.pt")
    with pytest.raises(EncoderError, match="does not exist; build one with `cosim encoder train"):
        load_encoder(tmp_path / "missing.pt")


class _Counting(FrozenEncoder):
    """Counts the forward passes of the trunk."""

    calls = 0

    def _trunk(self, chunk):
        type(self).calls += 1
        return super()._trunk(chunk)


def test_the_parallel_wrapper_encodes_every_step_in_one_forward_pass(encoder_file):
    plain = load_encoder(encoder_file[0])
    encoder = _Counting(plain.net)
    env = MultiColourBar([False, False, True], episode_length=4)
    wrapped = EncodedObservation(MultiColourBar([False, False, True], episode_length=4), encoder)
    assert wrapped.observation_space("agent_0") == gym.spaces.Box(0, np.inf, (512,), np.float32)
    raw, _ = env.reset(seed=3)
    obs, _ = wrapped.reset(seed=3)
    _Counting.calls = 0
    steps = 0
    while wrapped.agents:
        actions = {a: wrapped.action_space(a).sample() for a in wrapped.agents}
        obs, *_ = wrapped.step(actions)
        raw, *_ = env.step(actions)
        steps += 1
        for a in raw:  # each agent's features are its own frame's
            assert np.array_equal(obs[a], plain.encode(raw[a]))
    assert _Counting.calls == steps  # one forward per step for all its agents
    gym_env = EncodedGymObservation(ColourBar(False), plain)
    single, _ = gym_env.reset(seed=0)
    assert single.shape == (512,) and gym_env.observation_space.shape == (512,)
    with pytest.raises(EncoderError, match="takes 84x84x3 uint8 camera frames"):
        EncodedObservation(MultiColourBar([False], size=42), plain)


@pytest.mark.parametrize("algo", ["dqn", "td3"])
def test_heads_learn_on_the_features_with_the_algorithms_own_code(encoder_file, algo):
    encoder = load_encoder(encoder_file[0])
    trunk = {k: v.clone() for k, v in encoder.net.state_dict().items()}
    env = EncodedObservation(MultiColourBar([algo == "td3"] * 2, episode_length=8), encoder)
    cls, config = {"dqn": (DQN, DQNConfig(learning_starts=16, batch_size=8, train_freq=1, buffer_size=200,
                                          hidden=(32, 32), exploration_steps=50)),
                   "td3": (TD3, TD3Config(learning_starts=16, batch_size=8, buffer_size=200, hidden=(32, 32)))}[algo]
    agents = {a: cls.from_spaces(env.observation_space(a), env.action_space(a), config, seed=i)
              for i, a in enumerate(env.possible_agents)}
    fresh = cls.from_spaces(env.observation_space("agent_0"), env.action_space("agent_0"), config, seed=0)
    run_loop(agents, env, total_steps=60, seed=0)
    agent = agents["agent_0"]
    modules = [m for net in agent.networks.values() for m in net.modules()]
    assert not any(isinstance(m, NatureCNN | torch.nn.Conv2d) for m in modules)  # MLP heads on a vector
    assert any(isinstance(m, MLPEncoder) for m in modules)
    # the replay holds the float features, not frames
    assert agent.buffer.obs.dtype == np.float32 and agent.buffer.obs.shape[1:] == (512,) and len(agent.buffer) > 16
    trained, before = agent.state_dict()["networks"], fresh.state_dict()["networks"]
    assert any(not torch.equal(trained[n][k], before[n][k]) for n in trained for k in trained[n])  # heads learned
    assert all(torch.equal(v, trunk[k]) for k, v in encoder.net.state_dict().items())  # the encoder did not
