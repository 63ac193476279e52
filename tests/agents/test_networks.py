"""Networks: shapes, scaling, dueling aggregation, Polyak update."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from agents.networks import (
    ActorCritic,
    DeterministicActor,
    DuelingQNetwork,
    MLPEncoder,
    NatureCNN,
    QCritic,
    dueling_aggregate,
    make_encoder,
    obs_to_tensor,
    polyak_update,
)

IMAGE = gym.spaces.Box(0, 255, (84, 84, 3), np.uint8)
VECTOR = gym.spaces.Box(-1, 1, (4,), np.float32)


def test_dueling_aggregate_subtracts_mean_advantage():
    q = dueling_aggregate(torch.tensor([[1.0]]), torch.tensor([[1.0, 2.0, 3.0]]))
    torch.testing.assert_close(q, torch.tensor([[0.0, 1.0, 2.0]]))
    # Adding a constant to A must not change Q (identifiability of V and A).
    q2 = dueling_aggregate(torch.tensor([1.0]), torch.tensor([[11.0, 12.0, 13.0]]))
    torch.testing.assert_close(q2, q)


def test_polyak_update_interpolates_and_tau_one_copies():
    params = [torch.ones(3), torch.full((2,), 2.0)]
    targets = [torch.zeros(3), torch.zeros(2)]
    polyak_update(params, targets, 0.1)
    torch.testing.assert_close(targets[0], torch.full((3,), 0.1))
    torch.testing.assert_close(targets[1], torch.full((2,), 0.2))
    polyak_update(params, targets, 1.0)
    torch.testing.assert_close(targets[1], params[1])
    with pytest.raises(ValueError, match="tau"):
        polyak_update(params, targets, 1.5)


def test_nature_cnn_scales_uint8_and_infers_flatten_size():
    cnn = NatureCNN((84, 84, 3))
    assert cnn.features_dim == 512
    x = torch.randint(0, 256, (2, 84, 84, 3), dtype=torch.uint8)
    torch.testing.assert_close(cnn(x), cnn(x.float()))
    assert NatureCNN((36, 48, 3))(torch.zeros(1, 36, 48, 3)).shape == (1, 512)
    with pytest.raises(ValueError, match="36x36"):
        NatureCNN((20, 20, 3))


def test_make_encoder_picks_by_rank():
    assert isinstance(make_encoder(IMAGE), NatureCNN)
    enc = make_encoder(VECTOR)
    assert isinstance(enc, MLPEncoder) and enc.features_dim == 64


def test_obs_to_tensor_keeps_uint8_and_floats_others():
    assert obs_to_tensor(np.zeros((1, 2), np.uint8), "cpu").dtype == torch.uint8
    assert obs_to_tensor(np.zeros((1, 2), np.float64), "cpu").dtype == torch.float32


@pytest.mark.parametrize("space", [IMAGE, VECTOR])
def test_heads_output_shapes(space):
    obs = torch.zeros((5, *space.shape))
    logits, value = ActorCritic(space, 3)(obs)
    assert logits.shape == (5, 3) and value.shape == (5,)
    assert DuelingQNetwork(space, 3)(obs).shape == (5, 3)
    box = gym.spaces.Box(np.array([-2.0, 0.0], np.float32), np.array([2.0, 10.0], np.float32))
    actions = DeterministicActor(space, box)(obs)
    assert actions.shape == (5, 2)
    assert QCritic(space, box)(obs, actions).shape == (5,)


def test_deterministic_actor_respects_general_box_bounds():
    box = gym.spaces.Box(np.array([-2.0, 0.0], np.float32), np.array([2.0, 10.0], np.float32))
    actor = DeterministicActor(VECTOR, box)
    obs = torch.randn(16, 4, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        actor.mu.bias.fill_(1e3)  # saturate tanh at +1 -> the upper bounds
        torch.testing.assert_close(actor(obs), torch.tensor([[2.0, 10.0]]).expand(16, 2))
        actor.mu.bias.fill_(-1e3)
        torch.testing.assert_close(actor(obs), torch.tensor([[-2.0, 0.0]]).expand(16, 2))
        actor.mu.bias.zero_()
        actor.mu.weight.zero_()  # tanh(0) -> the middle of the box
        torch.testing.assert_close(actor(obs), torch.tensor([[0.0, 5.0]]).expand(16, 2))
