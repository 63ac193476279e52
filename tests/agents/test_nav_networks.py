"""Every network takes ``Dict(image, measurements)`` through a Nature CNN and a small MLP whose
features are joined (agents/networks.py; docs/task.md, "Observation")."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from agents.networks import (
    MEASUREMENT_FEATURES,
    NATURE_CNN_FEATURES,
    ActorCritic,
    DeterministicActor,
    DuelingQNetwork,
    ImageMeasurementsEncoder,
    QEnsemble,
    encoder_features_dim,
    make_encoder,
    obs_to_tensor,
)

SPACE = gym.spaces.Dict({"image": gym.spaces.Box(0, 255, (84, 84, 12), np.uint8),
                         "measurements": gym.spaces.Box(0.0, 2.0, (7,), np.float32)})
ACTIONS = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)


def _batch(measurements: np.ndarray) -> dict:
    image = np.random.default_rng(0).integers(0, 255, (len(measurements), 84, 84, 12), dtype=np.uint8)
    return obs_to_tensor({"image": image, "measurements": measurements.astype(np.float32)}, "cpu")


def test_the_encoder_joins_cnn_and_measurement_features():
    enc = make_encoder(SPACE)
    assert isinstance(enc, ImageMeasurementsEncoder)
    assert enc.features_dim == encoder_features_dim(SPACE) == NATURE_CNN_FEATURES + MEASUREMENT_FEATURES
    obs = _batch(np.zeros((3, 7)))
    assert obs["image"].dtype == torch.uint8 and obs["measurements"].dtype == torch.float32
    assert enc(obs).shape == (3, NATURE_CNN_FEATURES + MEASUREMENT_FEATURES)


@pytest.mark.parametrize("build", [
    lambda: ActorCritic(SPACE, 9), lambda: DuelingQNetwork(SPACE, 9),
    lambda: DeterministicActor(SPACE, ACTIONS), lambda: QEnsemble(SPACE, ACTIONS)])
def test_every_head_reads_the_measurements(build):
    """Same image, another route command: another output, and the MLP gets gradients."""
    torch.manual_seed(0)
    net = build()
    a, b = np.zeros((2, 7)), np.zeros((2, 7))
    a[:, 2], b[:, 4] = 1.0, 1.0  # "left" vs "right"
    run = (lambda o: net(o, torch.zeros(2, 2))) if isinstance(net, QEnsemble) else net
    out_a, out_b = (run(_batch(m)) for m in (a, b))
    out_a, out_b = (o[0] if isinstance(o, tuple) else o for o in (out_a, out_b))
    assert not torch.allclose(out_a, out_b)
    out_a.sum().backward()
    mlp = next(m for m in net.modules() if isinstance(m, ImageMeasurementsEncoder)).mlp
    assert mlp[0].weight.grad is not None and mlp[0].weight.grad.abs().sum() > 0


def test_other_dict_spaces_are_refused_naming_the_supported_one():
    with pytest.raises(ValueError, match=r"Dict\(image, measurements\) only"):
        make_encoder(gym.spaces.Dict({"camera": SPACE["image"]}))
