"""agents/imitation.py: behaviour cloning fits an actor-critic's policy to demonstrated actions
and its value to their returns, from a nav observation; other agents are refused."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from agents.imitation import clone
from agents.registry import get_agent_class

from .conftest import FAST, SPACES

SPACE = gym.spaces.Dict({"image": gym.spaces.Box(0, 255, (36, 36, 3), np.uint8),
                         "measurements": gym.spaces.Box(-1.0, 1.0, (7,), np.float32)})


def _demos(n: int, seed: int):
    """Actions and returns that only the measurements tell (the image is noise), as a route
    command tells a car which way to turn."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(-1, 1, (n, 7)).astype(np.float32)
    obs = {"image": rng.integers(0, 255, (n, 36, 36, 3), dtype=np.uint8), "measurements": m}
    return obs, m[:, :3].argmax(1) * 3, (2.0 * m[:, 3]).astype(np.float32)  # actions 0, 3, 6 of Discrete(9)


def test_cloning_fits_actions_and_returns_and_leaves_the_agents_optimizer_alone():
    agent = get_agent_class("ppo").from_spaces(SPACE, gym.spaces.Discrete(9), seed=0)
    obs, actions, returns = _demos(2000, 0)
    test_obs, test_actions, test_returns = _demos(300, 1)
    seen = []
    metrics = clone(agent, obs, actions, returns, epochs=12, batch_size=64, learning_rate=1e-3,
                    on_epoch=lambda e, m: seen.append(m["accuracy"]))
    assert len(seen) == 12 and seen[-1] > 0.9 > seen[0] and metrics["accuracy"] == seen[-1]
    picked = np.array([agent.act({"image": test_obs["image"][i], "measurements": test_obs["measurements"][i]},
                                 deterministic=True) for i in range(300)])
    assert (picked == test_actions).mean() > 0.8  # generalises to states it did not see (chance: 1/3)
    with torch.no_grad():
        _, values = agent.net({"image": torch.as_tensor(test_obs["image"]),
                               "measurements": torch.as_tensor(test_obs["measurements"])})
    assert np.corrcoef(values.numpy(), test_returns)[0, 1] > 0.8
    assert not agent.optimizer.state_dict()["state"]  # its own optimizer trained the network


def test_cloning_refuses_agents_without_an_actor_critic_and_mismatched_returns():
    dqn = get_agent_class("dqn").from_spaces(*SPACES["dqn"], config=FAST["dqn"], seed=0)
    with pytest.raises(ValueError, match="actor-critic agent .* got 'dqn'"):
        clone(dqn, np.zeros((4, 4), np.float32), np.zeros(4))
    ppo = get_agent_class("ppo").from_spaces(*SPACES["ppo"], config=FAST["ppo"], seed=0)
    with pytest.raises(ValueError, match="as many returns as actions"):
        clone(ppo, np.zeros((4, 4), np.float32), np.zeros(4), np.zeros(3))


def test_a_list_of_batches_trains_as_their_concatenation():
    """Demonstrations gathered in rounds (DAgger) are passed as a list and never copied into
    one array; the network learns exactly what it learns from the concatenated batch."""
    obs, actions, returns = _demos(300, 2)
    parts = [{k: v[a:b] for k, v in obs.items()} for a, b in ((0, 100), (100, 130), (130, 300))]
    nets = []
    for batch in (obs, parts):
        agent = get_agent_class("ppo").from_spaces(SPACE, gym.spaces.Discrete(9), seed=0)
        clone(agent, batch, actions, returns, epochs=2, batch_size=32, seed=5)
        nets.append(agent.net.state_dict())
    for key, tensor in nets[0].items():
        assert torch.equal(tensor, nets[1][key]), key
    agent = get_agent_class("ppo").from_spaces(SPACE, gym.spaces.Discrete(9), seed=0)
    with pytest.raises(ValueError, match="got 130 observations and 300 actions"):
        clone(agent, parts[:2], actions)
