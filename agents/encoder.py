"""A frozen perception encoder: a Nature CNN trained once by supervised learning, whose
features every algorithm learns its heads on (docs/task.md, "The frozen perception encoder").

:class:`EncoderNet` is the model: the end-to-end track's own :class:`~agents.networks.NatureCNN`
on one ``(H, W, 3)`` frame (512 features) and a linear head to the training labels, used only
while it is trained (eval/training/encoder.py trains it on the simulator's labels).
:func:`save_encoder` writes it as one file (``torch.save`` of tensors and plain values, so
:func:`load_encoder` reads it with ``weights_only=True``); the file's identity is its content
hash, :func:`file_sha256` (the SHA-256 of its bytes), which a training run records and a test
checks. :class:`FrozenEncoder` is a loaded trunk, frozen (eval mode, no gradients), that maps
a batch of frames to float32 feature vectors (:meth:`FrozenEncoder.encode`).

The same frame always gives the same features, bit for bit, whatever else is encoded with it:
frames go through the network in chunks of :data:`CHUNK` rows, the last chunk padded with
zeros, so one frame alone (a test's AC) and the same frame among a step's ACs (training) run
the identical computation (CPU convolutions pick their algorithm by batch size: a batch of
one differed from a batch of six by ~1e-6 here).

:class:`EncodedObservation` (a PettingZoo-parallel env) and :class:`EncodedGymObservation` (a
Gymnasium env) wrap an env whose observations are such frames: each step's frames of all
agents go through the encoder in one forward pass, and each agent observes
``Box(0, inf, (512,), float32)``. An algorithm then builds its MLP heads on a flat vector,
exactly as on any vector observation (agents/networks.py ``make_encoder``), and its replay
buffer stores float features, not frames.

Only torch, numpy and Gymnasium spaces: the simulator is invisible here; the wrappers are
duck-typed (no PettingZoo import).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch
from torch import nn

from agents.errors import AgentError
from agents.networks import NATURE_CNN_FEATURES, NatureCNN, layer_init

__all__ = ["CHUNK", "FORMAT", "FORMAT_VERSION", "EncodedGymObservation", "EncodedObservation", "EncoderError",
           "EncoderNet", "FrozenEncoder", "file_sha256", "load_encoder", "save_encoder"]

FORMAT = "cosim-frame-encoder"
FORMAT_VERSION = 1
CHUNK = 8
"""Rows per forward pass of :meth:`FrozenEncoder.encode` (the last chunk zero-padded): every
frame goes through the same computation whatever else is encoded with it (module docstring);
8 >= the six ACs of a step, so a training step is one forward pass."""


class EncoderError(AgentError):
    """An encoder file is missing, not an encoder, or not the one expected (its hash differs)."""


class EncoderNet(nn.Module):
    """The Nature CNN on one frame and a linear head to ``n_labels`` normalised labels.

    ``forward(frames)`` returns ``(features (B, 512), predictions (B, n_labels))``; only the
    trunk (``self.trunk``) is used once trained (:class:`FrozenEncoder`).
    """

    def __init__(self, image_shape: Sequence[int], n_labels: int, features_dim: int = NATURE_CNN_FEATURES):
        super().__init__()
        self.image_shape = tuple(int(d) for d in image_shape)
        self.trunk = NatureCNN(self.image_shape, features_dim)
        self.head = layer_init(nn.Linear(features_dim, int(n_labels)), std=1.0)

    def forward(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        features = self.trunk(frames)
        return features, self.head(features)


def file_sha256(path: str | Path) -> str:
    """The SHA-256 (hex) of a file's bytes: an encoder's identity, recorded by a run."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def save_encoder(path: str | Path, net: EncoderNet, *, labels: Sequence[str], mean: np.ndarray,
                 std: np.ndarray, obs: str = "image", info: Mapping[str, Any] | None = None) -> str:
    """Write a trained :class:`EncoderNet` to ``path`` (atomically: ``<path>.tmp``, then renamed)
    with its label names, the normalisation of its labels (``mean``, ``std`` per label), the
    camera variant its frames came from (``obs``) and ``info`` (plain values: how it was made
    and its held-out error). Returns the file's :func:`file_sha256`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "image_shape": list(net.image_shape),
        "features_dim": int(net.trunk.features_dim), "obs": str(obs), "labels": [str(n) for n in labels],
        "label_mean": torch.as_tensor(np.asarray(mean, np.float32)),
        "label_std": torch.as_tensor(np.asarray(std, np.float32)),
        "trunk": {k: v.detach().cpu().clone() for k, v in net.trunk.state_dict().items()},
        "head": {k: v.detach().cpu().clone() for k, v in net.head.state_dict().items()},
        "info": dict(info or {}),
    }
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise EncoderError(f"cannot write the encoder {path} ({exc.strerror or exc}); free space or "
                           "choose another --out") from exc
    return file_sha256(path)


class FrozenEncoder:
    """A trained encoder's trunk, frozen: frames in, float32 features out.

    Attributes:
        path, sha256: the file it was loaded from and that file's hash.
        image_shape: ``(H, W, C)`` of the frames it takes; features_dim: 512.
        obs: the camera variant of the frames it was trained on ("image", ...).
        labels, label_mean, label_std: what its (training-only) head predicts.
        info: how it was made (frames, epochs, held-out error; eval/training/encoder.py).
    """

    def __init__(self, net: EncoderNet, *, path: str | Path | None = None, sha256: str | None = None,
                 obs: str = "image", labels: Sequence[str] = (), label_mean=None, label_std=None,
                 info: Mapping[str, Any] | None = None, threads: int | None = None):
        self.net = net.eval()
        for p in self.net.parameters():
            p.requires_grad_(False)
        self.path = None if path is None else Path(path)
        self.sha256, self.obs, self.labels = sha256, obs, tuple(labels)
        self.image_shape = net.image_shape
        self.features_dim = int(net.trunk.features_dim)
        self.label_mean = None if label_mean is None else np.asarray(label_mean, np.float32)
        self.label_std = None if label_std is None else np.asarray(label_std, np.float32)
        self.info = dict(info or {})
        self.threads = threads

    def feature_space(self) -> gymnasium.spaces.Box:
        """The space of one frame's features: ``Box(0, inf, (512,), float32)`` (after the ReLU)."""
        return gymnasium.spaces.Box(0.0, np.inf, (self.features_dim,), np.float32)

    def check_frames(self, space: gymnasium.Space, what: str = "the observations") -> None:
        """Refuse a space whose observations are not this encoder's frames, naming both."""
        shape = tuple(getattr(space, "shape", None) or ())
        if shape != self.image_shape or getattr(space, "dtype", None) != np.uint8:
            raise EncoderError(f"encoder {self.path or ''} takes {'x'.join(map(str, self.image_shape))} uint8 "
                               f"camera frames but {what} are {space}; give it single camera frames "
                               f"(frame stack 1, camera size {self.image_shape[0]})")

    def _trunk(self, chunk: torch.Tensor) -> torch.Tensor:
        return self.net.trunk(chunk)

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """Features ``(B, 512)`` float32 of frames ``(B, H, W, C)`` (or one frame ``(H, W, C)``
        -> ``(512,)``), in chunks of :data:`CHUNK` (module docstring), without gradients."""
        frames = np.asarray(frames)
        single = frames.ndim == len(self.image_shape)
        batch = frames[None] if single else frames
        n = len(batch)
        out = np.empty((n, self.features_dim), np.float32)
        if self.threads is not None and torch.get_num_threads() != self.threads:
            torch.set_num_threads(self.threads)
        with torch.no_grad():
            for start in range(0, n, CHUNK):
                part = batch[start:start + CHUNK]
                padded = np.zeros((CHUNK, *self.image_shape), np.uint8)
                padded[:len(part)] = part
                out[start:start + len(part)] = self._trunk(torch.as_tensor(padded)).numpy()[:len(part)]
        return out[0] if single else out

    def predict(self, frames: np.ndarray) -> np.ndarray:
        """The head's labels of frames, in the labels' own units (for checks and the docs)."""
        with torch.no_grad():
            features = torch.as_tensor(np.atleast_2d(self.encode(frames)))
            normalised = self.net.head(features).numpy()
        out = normalised * self.label_std + self.label_mean
        return out[0] if np.asarray(frames).ndim == len(self.image_shape) else out


def load_encoder(path: str | Path, expected_sha256: str | None = None, threads: int | None = None) -> FrozenEncoder:
    """The :class:`FrozenEncoder` in ``path`` (on the CPU).

    ``expected_sha256``: the hash a run recorded; a file with another is refused.
    ``threads``: torch threads its forward passes run on (None: the process's setting).

    Raises:
        EncoderError: missing, unreadable or not an encoder file, another format version, or
            another hash than ``expected_sha256``; the message names the file and the fix.
    """
    path = Path(path)
    fix = "build one with `cosim encoder train --out FILE`"
    if not path.is_file():
        raise EncoderError(f"encoder {path} does not exist; {fix}")
    sha = file_sha256(path)
    if expected_sha256 is not None and sha != expected_sha256:
        raise EncoderError(f"encoder {path} has sha256 {sha[:12]}..., not the {expected_sha256[:12]}... it "
                           "was recorded with: the file was rebuilt or replaced; give the encoder file that "
                           "run was trained on, or train again with this one")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch.load of arbitrary bytes raises anything
        raise EncoderError(f"encoder {path} is not readable ({type(exc).__name__}); {fix}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise EncoderError(f"{path} is not a cosim frame encoder (no '{FORMAT}' header); {fix}")
    if payload.get("format_version") != FORMAT_VERSION:
        raise EncoderError(f"encoder {path} has format version {payload.get('format_version')}, this cosim "
                           f"reads {FORMAT_VERSION}; {fix}")
    labels = list(payload["labels"])
    net = EncoderNet(payload["image_shape"], len(labels), int(payload["features_dim"]))
    net.trunk.load_state_dict(payload["trunk"])
    net.head.load_state_dict(payload["head"])
    return FrozenEncoder(net, path=path, sha256=sha, obs=str(payload.get("obs", "image")), labels=labels,
                         label_mean=payload["label_mean"].numpy(), label_std=payload["label_std"].numpy(),
                         info=payload.get("info", {}), threads=threads)


class EncodedObservation:
    """A PettingZoo-parallel env whose agents observe the :class:`FrozenEncoder` features of
    the frames ``env`` gives them: every reset and step, the frames of all agents in it are
    encoded together (one forward pass up to :data:`CHUNK` agents) and each agent gets its
    ``(512,)`` float32 vector. Everything else is ``env``'s (attributes are forwarded)."""

    def __init__(self, env, encoder: FrozenEncoder):
        self.env, self.encoder = env, encoder
        for agent in env.possible_agents:
            encoder.check_frames(env.observation_space(agent), f"agent {agent}'s observations")
        self._space = encoder.feature_space()

    def __getattr__(self, name: str):
        if name.startswith("_") or name in ("env", "encoder"):
            raise AttributeError(name)
        return getattr(self.env, name)

    @property
    def unwrapped(self):
        return getattr(self.env, "unwrapped", self.env)

    @property
    def agents(self) -> list:
        return self.env.agents

    @property
    def possible_agents(self) -> list:
        return self.env.possible_agents

    def observation_space(self, agent) -> gymnasium.spaces.Box:
        return self._space

    def action_space(self, agent):
        return self.env.action_space(agent)

    def reset(self, seed=None, options=None):
        obs, infos = self.env.reset(seed=seed, options=options)
        return self._encode(obs), infos

    def step(self, actions):
        obs, rewards, terms, truncs, infos = self.env.step(actions)
        return self._encode(obs), rewards, terms, truncs, infos

    def render(self):
        return self.env.render()

    def close(self) -> None:
        self.env.close()

    def _encode(self, obs: Mapping) -> dict:
        if not obs:
            return {}
        names = list(obs)
        features = self.encoder.encode(np.stack([obs[a] for a in names]))
        return {a: features[i] for i, a in enumerate(names)}


class EncodedGymObservation(gymnasium.ObservationWrapper):
    """A Gymnasium env whose observation (one frame) is replaced by its encoder features."""

    def __init__(self, env: gymnasium.Env, encoder: FrozenEncoder):
        super().__init__(env)
        encoder.check_frames(env.observation_space)
        self.encoder = encoder
        self.observation_space = encoder.feature_space()

    def observation(self, observation):
        return self.encoder.encode(observation)
