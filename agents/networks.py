"""Shared PyTorch building blocks for every algorithm in ``agents``.

Encoders turn an observation batch into a feature vector: :class:`NatureCNN`
(Mnih et al. 2015) for ``(H, W, C)`` images, :class:`ImageMeasurementsEncoder` for an
image with a measurements vector (``Dict(image, measurements)``: the CNN's features joined
to a small MLP's), :class:`MLPEncoder` for flat vectors; :func:`make_encoder` picks one
from the observation space. The heads
built on them are the ones the algorithms need: :class:`ActorCritic` (PPO, A3C,
IMPALA), :class:`DuelingQNetwork` (DQN), :class:`DeterministicActor` and
:class:`QCritic` / :class:`QEnsemble` (DDPG, TD3). :func:`polyak_update` is the soft target update.

Only torch, numpy and Gymnasium spaces are used here: the driving simulator is
invisible to this package.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import gymnasium
import numpy as np
import torch
from torch import nn

from agents.observations import NAV_KEYS, is_nav_space

NATURE_CNN_FEATURES = 512

__all__ = [
    "ActorCritic",
    "DeterministicActor",
    "DuelingQNetwork",
    "MLPEncoder",
    "NatureCNN",
    "QCritic",
    "QEnsemble",
    "dueling_aggregate",
    "encoder_features_dim",
    "layer_init",
    "make_encoder",
    "obs_to_tensor",
    "polyak_update",
    "scaled_image",
]


def layer_init(layer: nn.Module, std: float = float(np.sqrt(2)), bias: float = 0.0) -> nn.Module:
    """Orthogonal weight init with a constant bias (the CleanRL/SB3 default).

    Args:
        layer: An ``nn.Linear`` or ``nn.Conv2d``.
        std: Gain of the orthogonal init; sqrt(2) suits ReLU layers, small values
            (0.01) suit policy-logit heads so the initial policy is near uniform.
        bias: Constant bias value.

    Returns:
        The same layer, initialised in place.
    """
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias)
    return layer


class NatureCNN(nn.Module):
    """The Nature-DQN convolutional encoder for ``(H, W, C)`` images.

    Accepts uint8 or float observations with values in 0..255 in channel-last
    layout (what the environment emits), permutes them to NCHW and scales them
    to 0..1 inside the network, so buffers can keep compact uint8 copies.

    Attributes:
        features_dim: Size of the output feature vector.
    """

    def __init__(self, obs_shape: tuple[int, int, int], features_dim: int = NATURE_CNN_FEATURES):
        super().__init__()
        if len(obs_shape) != 3:
            raise ValueError(f"NatureCNN needs an (H, W, C) observation shape, got {obs_shape}")
        height, width, channels = (int(d) for d in obs_shape)
        if min(height, width) < 36:
            raise ValueError(
                f"NatureCNN needs images of at least 36x36 (8/4, 4/2, 3/1 convolutions), "
                f"got {height}x{width}; resize the observation or use a smaller encoder"
            )
        self.cnn = nn.Sequential(
            layer_init(nn.Conv2d(channels, 32, kernel_size=8, stride=4)),
            nn.ReLU(),
            layer_init(nn.Conv2d(32, 64, kernel_size=4, stride=2)),
            nn.ReLU(),
            layer_init(nn.Conv2d(64, 64, kernel_size=3, stride=1)),
            nn.ReLU(),
            nn.Flatten(),
        )
        # Infer the flatten size with a dummy forward pass (SB3 style) instead of
        # hard-coding 3136, so any image size that survives the strides works.
        with torch.no_grad():
            n_flatten = self.cnn(torch.zeros(1, channels, height, width)).shape[1]
        self.linear = nn.Sequential(layer_init(nn.Linear(n_flatten, features_dim)), nn.ReLU())
        self.features_dim = features_dim

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Encode a batch ``(B, H, W, C)`` of images with values 0..255."""
        return self.linear(self.cnn(scaled_image(obs)))


def scaled_image(obs: torch.Tensor) -> torch.Tensor:
    """``obs.float().permute(0, 3, 1, 2) / 255.0`` for channel-last images, bit for bit, in one
    float copy instead of two: the uint8 batch is converted once and scaled in place (a float32
    batch, the caller's, is scaled into a new tensor). The result is an NCHW view of
    channels-last memory, which oneDNN's convolutions take as it is. For a PPO minibatch of 64
    84x84x12 images 2-3x faster than the two copies (docs/benchmarks.md, issue 59)."""
    x = obs.permute(0, 3, 1, 2)
    if x.dtype == torch.float32:
        return x / 255.0
    return x.to(torch.float32).div_(255.0)


class MLPEncoder(nn.Module):
    """An MLP for flat observation vectors (tanh by default, as in PPO's MLP policies).

    Attributes:
        features_dim: Size of the output feature vector (the last hidden width).
    """

    def __init__(
        self, obs_dim: int, hidden: tuple[int, ...] = (64, 64), activation: type[nn.Module] = nn.Tanh
    ):
        super().__init__()
        if obs_dim < 1 or not hidden:
            raise ValueError(f"MLPEncoder needs obs_dim >= 1 and >= 1 hidden layer, got {obs_dim}, {hidden}")
        layers: list[nn.Module] = []
        width = obs_dim
        for size in hidden:
            layers += [layer_init(nn.Linear(width, size)), activation()]
            width = size
        self.net = nn.Sequential(*layers)
        self.features_dim = width

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Encode a batch ``(B, obs_dim)`` (extra trailing dims are flattened)."""
        return self.net(obs.float().flatten(1))


MEASUREMENT_FEATURES = 64
"""Width of the small MLP on the measurements vector, joined to the CNN's features."""


def _is_image_space(observation_space) -> bool:
    """An image, or an image with measurements: the encoders that start with a Nature CNN."""
    return is_nav_space(observation_space) or len(observation_space.shape) == 3


class ImageMeasurementsEncoder(nn.Module):
    """A Nature CNN on the image and a small MLP on the measurements vector, their features
    concatenated (the conditional-imitation-learning and MetaDrive recipe; docs/task.md,
    "Observation"). Takes a dict batch ``{"image": (B, H, W, C), "measurements": (B, M)}``.

    Attributes:
        features_dim: 512 CNN features + :data:`MEASUREMENT_FEATURES`.
    """

    def __init__(self, image_shape: tuple[int, int, int], measurements_dim: int,
                 hidden: int = MEASUREMENT_FEATURES):
        super().__init__()
        self.cnn = NatureCNN(image_shape)
        self.mlp = nn.Sequential(layer_init(nn.Linear(int(measurements_dim), hidden)), nn.ReLU())
        self.features_dim = self.cnn.features_dim + hidden

    def forward(self, obs) -> torch.Tensor:
        return torch.cat([self.cnn(obs["image"]), self.mlp(obs["measurements"].float())], dim=-1)


def make_encoder(
    observation_space: gymnasium.spaces.Box,
    hidden: tuple[int, ...] = (64, 64),
    activation: type[nn.Module] = nn.Tanh,
) -> nn.Module:
    """Build the encoder suited to an observation space.

    Args:
        observation_space: A Box; 3-D shapes are treated as ``(H, W, C)`` images.
        hidden: Hidden sizes for the MLP encoder (ignored for images).
        activation: Activation class of the MLP encoder (ignored for images).

    Returns:
        A module with a ``features_dim`` attribute: :class:`NatureCNN` for images,
        :class:`ImageMeasurementsEncoder` for ``Dict(image, measurements)``,
        :class:`MLPEncoder` otherwise.

    Raises:
        ValueError: If the space is not a Box.
    """
    if is_nav_space(observation_space):
        return ImageMeasurementsEncoder(tuple(observation_space["image"].shape),
                                        observation_space["measurements"].shape[0])
    if not isinstance(observation_space, gymnasium.spaces.Box):
        raise ValueError(
            f"agents support Box observation spaces and Dict({', '.join(NAV_KEYS)}) only, got "
            f"{observation_space!r}; flatten other Dict/Tuple observations with a gymnasium wrapper first"
        )
    if _is_image_space(observation_space):
        return NatureCNN(tuple(observation_space.shape))
    return MLPEncoder(int(np.prod(observation_space.shape)), hidden, activation)


def encoder_features_dim(observation_space: gymnasium.spaces.Box) -> int:
    """Width of what :class:`QEnsemble` ``.encode`` returns: 512 for images (+ the measurement
    features for ``Dict(image, measurements)``), the flat size otherwise."""
    if is_nav_space(observation_space):
        return NATURE_CNN_FEATURES + MEASUREMENT_FEATURES
    if _is_image_space(observation_space):
        return NATURE_CNN_FEATURES
    return int(np.prod(observation_space.shape))


def obs_to_tensor(obs: np.ndarray, device) -> torch.Tensor:
    """Convert an observation batch to a tensor on ``device``.

    uint8 images stay uint8 (4x less to copy; the encoder scales them), every
    other dtype becomes float32. No batch dimension is added. A dict (an image with
    measurements) becomes a dict of tensors.
    """
    if isinstance(obs, Mapping):
        return {key: obs_to_tensor(value, device) for key, value in obs.items()}
    array = np.asarray(obs)
    if array.dtype == np.uint8:
        return torch.as_tensor(array, device=device)
    return torch.as_tensor(array, dtype=torch.float32, device=device)


class ActorCritic(nn.Module):
    """Encoder(s) with a categorical policy head and a state-value head.

    Images share one Nature CNN between policy and value (the Atari recipe);
    vector observations get separate policy and value MLPs by default (the
    CleanRL/SB3 MLP recipe: a large value loss then cannot disturb the policy's
    features). ``share_encoder`` overrides either choice.
    """

    def __init__(
        self,
        observation_space,
        n_actions: int,
        hidden: tuple[int, ...] = (64, 64),
        share_encoder: bool | None = None,
    ):
        super().__init__()
        if share_encoder is None:
            share_encoder = _is_image_space(observation_space)
        self.encoder = make_encoder(observation_space, hidden)
        self.value_encoder = None if share_encoder else make_encoder(observation_space, hidden)
        self.policy_head = layer_init(nn.Linear(self.encoder.features_dim, n_actions), std=0.01)
        self.value_head = layer_init(nn.Linear(self.encoder.features_dim, 1), std=1.0)

    def forward(self, obs: torch.Tensor, value_grad: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
        """Return ``(logits (B, n_actions), value (B,))``.

        ``value_grad`` scales the gradient that the value reaches a shared encoder with (the
        value head's own gradient and every output stay as they are; separate encoders ignore
        it): PPO's ``shared_value_grad``."""
        features = self.encoder(obs)
        if self.value_encoder is not None:
            value_features = self.value_encoder(obs)
        elif value_grad == 1.0:
            value_features = features
        else:  # the same values (f + s * 0); the gradient into the encoder times s
            frozen = features.detach()
            value_features = frozen + value_grad * (features - frozen)
        return self.policy_head(features), self.value_head(value_features).squeeze(-1)


def dueling_aggregate(value: torch.Tensor, advantages: torch.Tensor) -> torch.Tensor:
    """Combine dueling streams: ``Q = V + A - mean(A)`` (Wang et al. 2016, eq. 9).

    Args:
        value: ``(B, 1)`` or ``(B,)`` state values.
        advantages: ``(B, n_actions)`` action advantages.

    Returns:
        ``(B, n_actions)`` Q-values.
    """
    if value.dim() == 1:
        value = value.unsqueeze(-1)
    return value + advantages - advantages.mean(dim=-1, keepdim=True)


class DuelingQNetwork(nn.Module):
    """Encoder followed by separate value and advantage streams."""

    def __init__(self, observation_space, n_actions: int, hidden: tuple[int, ...] = (64, 64)):
        super().__init__()
        # ReLU for value regression (DQN/SB3 QNetwork); tanh MLPs saturate on large Q targets.
        self.encoder = make_encoder(observation_space, hidden, nn.ReLU)
        width = self.encoder.features_dim
        self.value_head = layer_init(nn.Linear(width, 1), std=1.0)
        self.advantage_head = layer_init(nn.Linear(width, n_actions), std=1.0)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Return Q-values ``(B, n_actions)``."""
        features = self.encoder(obs)
        return dueling_aggregate(self.value_head(features), self.advantage_head(features))


def _check_box(action_space) -> None:
    if not isinstance(action_space, gymnasium.spaces.Box) or len(action_space.shape) != 1:
        raise ValueError(f"continuous agents need a 1-D Box action space, got {action_space!r}")
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        raise ValueError(f"action space bounds must be finite to scale tanh, got {action_space!r}")


class DeterministicActor(nn.Module):
    """Encoder + tanh head scaled to the Box bounds: ``a = mid + half_range * tanh(.)``."""

    def __init__(self, observation_space, action_space: gymnasium.spaces.Box, hidden: tuple[int, ...] = (256, 256)):
        super().__init__()
        _check_box(action_space)
        self.encoder = make_encoder(observation_space, hidden, nn.ReLU)
        self.mu = layer_init(nn.Linear(self.encoder.features_dim, action_space.shape[0]), std=0.01)
        low = torch.as_tensor(action_space.low, dtype=torch.float32)
        high = torch.as_tensor(action_space.high, dtype=torch.float32)
        # Buffers, not parameters: they move with .to(device) and live in state_dict.
        self.register_buffer("action_scale", (high - low) / 2.0)
        self.register_buffer("action_bias", (high + low) / 2.0)

    def preactivation(self, obs: torch.Tensor) -> torch.Tensor:
        """The head's output before the tanh, ``(B, action_dim)``."""
        return self.mu(self.encoder(obs))

    def squash(self, preactivation: torch.Tensor) -> torch.Tensor:
        """Map pre-tanh outputs into the Box bounds."""
        return self.action_bias + self.action_scale * torch.tanh(preactivation)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Return actions ``(B, action_dim)`` inside the Box bounds."""
        return self.squash(self.preactivation(obs))


class QEnsemble(nn.Module):
    """``n_critics`` state-action values ``Q_i(s, a) -> (n_critics, B)``.

    For images the heads share one Nature CNN (as SB3's ``ContinuousCritic``
    does); for vectors each head is its own MLP on ``concat(obs, action)``
    (CleanRL's TD3). Actions are normalised to [-1, 1] before concatenation so
    the critic sees the same scale whatever the Box bounds are.
    """

    def __init__(
        self,
        observation_space,
        action_space: gymnasium.spaces.Box,
        n_critics: int = 2,
        hidden: tuple[int, ...] = (256, 256),
    ):
        super().__init__()
        _check_box(action_space)
        if n_critics < 1:
            raise ValueError(f"QEnsemble needs n_critics >= 1, got {n_critics}")
        if _is_image_space(observation_space):
            self.encoder: nn.Module = make_encoder(observation_space)
            in_dim = self.encoder.features_dim
        else:
            self.encoder = nn.Flatten()
            in_dim = int(np.prod(observation_space.shape))
        in_dim += action_space.shape[0]
        self.heads = nn.ModuleList(_mlp(in_dim, hidden, 1) for _ in range(n_critics))
        low = torch.as_tensor(action_space.low, dtype=torch.float32)
        high = torch.as_tensor(action_space.high, dtype=torch.float32)
        self.register_buffer("action_scale", (high - low) / 2.0)
        self.register_buffer("action_bias", (high + low) / 2.0)

    def encode(self, obs: torch.Tensor) -> torch.Tensor:
        """Observation features shared by the heads (the CNN output for images)."""
        if isinstance(self.encoder, NatureCNN | ImageMeasurementsEncoder):
            return self.encoder(obs)
        return self.encoder(obs.float())

    def q_from_features(self, features: torch.Tensor, action: torch.Tensor, head: int) -> torch.Tensor:
        """``Q_head`` ``(B,)`` from precomputed :meth:`encode` features."""
        normalised = (action.float() - self.action_bias) / self.action_scale
        return self.heads[head](torch.cat([features, normalised], dim=-1)).squeeze(-1)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Return ``Q_i(obs, action)`` stacked to shape ``(n_critics, B)``."""
        features = self.encode(obs)
        return torch.stack([self.q_from_features(features, action, i) for i in range(len(self.heads))])


def _mlp(in_dim: int, hidden: tuple[int, ...], out_dim: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for size in hidden:
        layers += [layer_init(nn.Linear(in_dim, size)), nn.ReLU()]
        in_dim = size
    layers.append(layer_init(nn.Linear(in_dim, out_dim), std=1.0))
    return nn.Sequential(*layers)


class QCritic(nn.Module):
    """One state-action value ``Q(s, a) -> (B,)`` (a one-head :class:`QEnsemble`)."""

    def __init__(self, observation_space, action_space: gymnasium.spaces.Box, hidden: tuple[int, ...] = (256, 256)):
        super().__init__()
        self.ensemble = QEnsemble(observation_space, action_space, 1, hidden)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Return ``Q(obs, action)`` with shape ``(B,)``."""
        return self.ensemble(obs, action)[0]


@torch.no_grad()
def polyak_update(
    params: Iterable[torch.Tensor], target_params: Iterable[torch.Tensor], tau: float
) -> None:
    """Soft target update ``target <- tau * param + (1 - tau) * target``, in place.

    Args:
        params: Online parameters (e.g. ``net.parameters()``).
        target_params: Target parameters, same order and shapes.
        tau: Interpolation factor in [0, 1]; 1 copies the online weights.

    Raises:
        ValueError: If tau is outside [0, 1] or the two lists differ in length.
    """
    if not 0.0 <= tau <= 1.0:
        raise ValueError(f"polyak_update tau must be in [0, 1], got {tau}")
    params, target_params = list(params), list(target_params)
    if len(params) != len(target_params):
        raise ValueError(
            f"polyak_update got {len(params)} params but {len(target_params)} target params"
        )
    for param, target in zip(params, target_params, strict=True):
        target.mul_(1.0 - tau).add_(param, alpha=tau)
