"""The frozen perception encoder: its data, its supervised training (`cosim encoder train`) and
its use by a run (``--encoder``): docs/task.md, "The frozen perception encoder".

**Data** (:func:`collect`). Frames from every environment asked for (default all five), each
AC driven by the scripted autopilot (cosim.controller.Autopilot, continuous actions) with
perturbations (:class:`PerturbedAutopilot`): Gaussian noise on every action and, at a random
rate per AC and episode, held random excursions (a random throttle and steer held 5-25 steps),
so that off-lane, off-road and near-miss frames appear beside the autopilot's clean driving.
Each frame is one AC's single camera frame (the camera variant ``obs``, default image) at a
reset or step, stored uint8, and its label is the state track's vector of that AC at that
moment (cosim.state.state_vectors, the privileged 65 numbers ``--obs state`` observes),
computed from the same world while the cameras are on. Each environment gets an equal share
of the frames; its held-out share (``held_out``, default 10%) comes from episodes of their own
seeds, never trained on. Seeds: :data:`ENCODER_SEED` + 100,000 x seed + 1,000 x environment +
episode, apart from training's (< 10^9), validation's and the test's.

**Labels and loss** (:data:`LABEL_GROUPS`). Every number of the state vector but the previous
control (13-14: not in the frame) is a target, normalised per dimension with the training
frames' mean and standard deviation (stored in the encoder file). The x, y, vx, vy of a
neighbour slot (vehicles, pedestrians) count only where that slot holds an actor (its
``present`` flag; an empty slot's zeros are no position), the flag itself always. The loss is
the mean squared error of the normalised labels over the counted numbers. The held-out error
is reported per group (lane, route, speed, signal, vehicles, pedestrians) against predicting
the training mean (:func:`group_errors`).

**Model** (agents/encoder.py). The Nature CNN on one 84x84x3 frame (the end-to-end track's own
trunk) -> 512 features, a linear head to the labels for training only; Adam, minibatches,
a few epochs (:func:`fit`).

**Use** (:func:`observation`). A run with ``--encoder FILE`` (TrainConfig.encoder, its
SHA-256 in TrainConfig.encoder_sha256) builds the training, validation and demonstration envs
as cosim.wrappers.observation_wrappers does with one frame, then encodes every step's frames
of all ACs in one forward pass (agents.encoder.EncodedObservation) and stacks each AC's last K
feature vectors (cosim.wrappers.FrameStack, oldest first: ``(512 K,)`` float32). The test
drives such a checkpoint through eval.testing.rollout.EncodedPolicy, which does the same for
its AC (eval/testing/loading.py, refusing an encoder file with another hash than the run's).
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from eval.training.config import NOT_CAMERA, TrainConfig, TrainError

__all__ = ["ENCODER_SEED", "LABEL_GROUPS", "EncoderData", "PerturbedAutopilot", "build", "camera_variants",
           "collect", "fit", "group_errors", "label_names", "label_weights", "observation", "run_encoder"]

ENCODER_SEED = 1_000_000_000
"""First episode seed of the encoder's data: training episodes use ``seed + episode`` (< 10^9),
validation 1,999,000,000 and up, the test protocol and the validity suite small seeds."""
MAX_SEED = 9_000
"""The largest ``--seed`` of `cosim encoder train`: its seeds stay below validation's."""
LABEL_GROUPS: dict[str, tuple[str, ...]] = {
    "lane": ("lateral", "heading_error"),
    "route": ("path", "goal"),
    "speed": ("speed",),
    "signal": ("signal",),
    "vehicles": ("vehicles",),
    "pedestrians": ("pedestrians",),
}
"""The held-out error's groups: state-vector blocks (cosim.state.STATE_LAYOUT) per group. The
``control`` block (the previous action) is no target: nothing in a frame shows it."""
NOISE = 0.15
"""Standard deviation of the Gaussian noise on every autopilot action (throttle, steer)."""
EXCURSION_RATES = (0.0, 0.02, 0.05)
"""Per-step chances of starting a held random excursion; each AC draws one per episode."""
EXCURSION_STEPS = (5, 25)
"""Steps an excursion holds its random action (uniform, both ends included)."""


def camera_variants() -> tuple[str, ...]:
    """The ``--obs`` variants whose observation is camera frames an encoder takes."""
    from cosim.wrappers import OBS_VARIANTS

    return tuple(v for v in OBS_VARIANTS if v not in NOT_CAMERA)


def label_names() -> list[str]:
    """One name per number of the state vector (cosim.state.STATE_LAYOUT order)."""
    from cosim.state import NEIGHBOUR_FEATURES, STATE_DIM, STATE_LAYOUT

    names = [""] * STATE_DIM
    for block, span in STATE_LAYOUT.items():
        size = span.stop - span.start
        for j in range(size):
            if block in ("vehicles", "pedestrians"):
                k, f = divmod(j, len(NEIGHBOUR_FEATURES))
                names[span.start + j] = f"{block}[{k}].{NEIGHBOUR_FEATURES[f]}"
            else:
                names[span.start + j] = block if size == 1 else f"{block}[{j}]"
    return names


def label_weights(labels: np.ndarray) -> np.ndarray:
    """``(N, 65)`` float32 weights of the labels in the loss (module docstring): 0 for the
    previous control, a neighbour slot's x, y, vx, vy weighted by its ``present`` flag, else 1."""
    from cosim.state import NEIGHBOUR_FEATURES, STATE_LAYOUT

    labels = np.asarray(labels)
    w = np.ones(labels.shape, np.float32)
    w[:, STATE_LAYOUT["control"]] = 0.0
    per = len(NEIGHBOUR_FEATURES)
    for block in ("vehicles", "pedestrians"):
        span = STATE_LAYOUT[block]
        for start in range(span.start, span.stop, per):
            w[:, start + 1:start + per] = (labels[:, start] > 0.5)[:, None]
    return w


class PerturbedAutopilot:
    """The autopilot of one AC with noise and held random excursions (module docstring): the
    autopilot is asked every step (its waiting and creeping state goes on), its action gets
    N(0, NOISE) noise, and at ``rate`` per step an excursion starts, holding a random
    throttle in [-0.3, 1] and steer in [-1, 1] for EXCURSION_STEPS steps."""

    def __init__(self, world, ac: str, rng: np.random.Generator, rate: float):
        from cosim.controller import Autopilot

        self.pilot, self.rng, self.rate = Autopilot(world, ac), rng, float(rate)
        self.left, self.held = 0, np.zeros(2, np.float32)

    def act(self) -> np.ndarray:
        action = np.asarray(self.pilot.act(), np.float64)
        if self.left > 0:
            self.left -= 1
            return self.held
        if self.rate and self.rng.random() < self.rate:
            self.left = int(self.rng.integers(EXCURSION_STEPS[0], EXCURSION_STEPS[1] + 1)) - 1
            self.held = np.array([self.rng.uniform(-0.3, 1.0), self.rng.uniform(-1.0, 1.0)], np.float32)
            return self.held
        return np.clip(action + self.rng.normal(0.0, NOISE, 2), -1.0, 1.0).astype(np.float32)


@dataclass
class EncoderData:
    """Frames and their labels: ``frames`` (N, H, W, 3) uint8, ``labels`` (N, 65) float32,
    ``env`` (N,) the index in ``envs`` each came from, ``held_out`` (N,) bool."""

    frames: np.ndarray
    labels: np.ndarray
    env: np.ndarray
    held_out: np.ndarray
    envs: tuple[str, ...]

    @property
    def nbytes(self) -> int:
        return int(self.frames.nbytes + self.labels.nbytes + self.env.nbytes + self.held_out.nbytes)

    def save(self, path: Path) -> None:
        np.savez(path, frames=self.frames, labels=self.labels, env=self.env, held_out=self.held_out,
                 envs=np.array(self.envs))

    @classmethod
    def load(cls, path: Path) -> EncoderData:
        with np.load(path) as f:
            return cls(f["frames"], f["labels"], f["env"], f["held_out"], tuple(str(e) for e in f["envs"]))


def _shares(total: int, n: int) -> list[int]:
    return [total // n + (i < total % n) for i in range(n)]


class _Collector:
    """Fills the arrays of :func:`collect`, one environment at a time."""

    def __init__(self, frames: int, image_size: int, label_dim: int, tick: Callable[[int], None]):
        self.frames = np.zeros((frames, image_size, image_size, 3), np.uint8)
        self.labels = np.zeros((frames, label_dim), np.float32)
        self.env = np.zeros(frames, np.int16)
        self.held_out = np.zeros(frames, bool)
        self.filled, self.tick = 0, tick

    def store(self, base, obs: dict, budget: int, env_index: int, held: bool) -> int:
        """Store up to ``budget`` of ``obs``'s frames with their labels; return how many."""
        from cosim.state import state_vectors

        names = list(obs)[:budget]
        if not names:
            return 0
        labels = state_vectors(base.world, names, base.last_controls)
        at = slice(self.filled, self.filled + len(names))
        self.frames[at] = np.stack([obs[a] for a in names])
        self.labels[at], self.env[at], self.held_out[at] = labels, env_index, held
        self.filled += len(names)
        self.tick(len(names))
        return len(names)


def _drive(env, collector: _Collector, budget: int, seed: int, env_index: int, held: bool) -> int:
    """One perturbed-autopilot episode of ``env`` (seeded ``seed``), storing up to ``budget`` frames."""
    rng = np.random.default_rng(seed)
    base = env.unwrapped
    obs, _ = env.reset(seed=seed)
    drivers = {a: PerturbedAutopilot(base.world, a, rng, rng.choice(EXCURSION_RATES)) for a in env.possible_agents}
    stored = collector.store(base, obs, budget, env_index, held)
    while env.agents and stored < budget:
        obs, *_ = env.step({a: drivers[a].act() for a in env.agents})
        stored += collector.store(base, obs, budget - stored, env_index, held)
    return stored


def collect(envs: Sequence[str], frames: int, seed: int = 0, agents: int | None = None, obs: str = "image",
            horizon: int = 200, held_out: float = 0.1, image_size: int = 84,
            progress: bool = False) -> EncoderData:
    """``frames`` labelled frames from ``envs`` (module docstring), ``held_out`` of each
    environment's from episodes of their own; ``agents`` ACs per environment (None: every
    spawn point), episodes of at most ``horizon`` steps."""
    from tqdm import tqdm

    from cosim.state import STATE_DIM
    from cosim.wrappers import observation_wrappers
    from eval.testing.conditions import TestConditions

    bar = tqdm(total=frames, unit="frame", desc="encoder data", disable=not progress, dynamic_ncols=True)
    collector = _Collector(frames, image_size, STATE_DIM, bar.update)
    try:
        for i, (name, share) in enumerate(zip(envs, _shares(frames, len(envs)), strict=True)):
            hold = min(share - 1, max(1, round(held_out * share))) if held_out > 0 and share > 1 else 0
            # the test's conditions (a collision does not end the episode: the frames after a contact
            # are data too), in the scenario's traffic
            base = TestConditions.of(1, horizon).env(name, "continuous", agents, image_size=image_size,
                                                     seed=ENCODER_SEED + 100_000 * seed + 1_000 * i)
            env = observation_wrappers(base, frame_stack=1, obs=obs)
            try:
                space = env.observation_space(env.possible_agents[0])
                if len(getattr(space, "shape", ())) != 3 or space.dtype != np.uint8:
                    raise TrainError(f"--obs {obs} gives {space}, not camera frames; use one of "
                                     f"{', '.join(camera_variants())}")
                episode = 0
                for held, budget in ((False, share - hold), (True, hold)):
                    while budget > 0:
                        budget -= _drive(env, collector, budget, ENCODER_SEED + 100_000 * seed + 1_000 * i + episode,
                                         i, held)
                        episode += 1
            finally:
                env.close()
    finally:
        bar.close()
    n = collector.filled
    return EncoderData(collector.frames[:n], collector.labels[:n], collector.env[:n], collector.held_out[:n],
                       tuple(envs))


def normalisation(labels: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-dimension mean and standard deviation of the counted labels (a dimension that never
    varies gets 1, so its normalised target is 0)."""
    total = np.maximum(weights.sum(axis=0), 1.0)
    mean = (weights * labels).sum(axis=0) / total
    std = np.sqrt((weights * (labels - mean) ** 2).sum(axis=0) / total)
    return mean.astype(np.float32), np.where(std > 1e-6, std, 1.0).astype(np.float32)


def group_errors(predicted: np.ndarray, labels: np.ndarray, mean: np.ndarray, std: np.ndarray) -> dict[str, dict]:
    """Per group of :data:`LABEL_GROUPS`: the mean squared error of the normalised labels over
    the counted numbers (``mse``), that of predicting the training mean (``baseline``) and their
    ratio (``ratio``: 1 = no better than the mean, 0 = exact), and how many numbers counted."""
    from cosim.state import STATE_LAYOUT

    w = label_weights(labels)
    err = w * ((predicted - labels) / std) ** 2
    base = w * ((labels - mean) / std) ** 2
    out = {}
    for group, blocks in LABEL_GROUPS.items():
        cols = np.concatenate([np.arange(STATE_LAYOUT[b].start, STATE_LAYOUT[b].stop) for b in blocks])
        count = float(w[:, cols].sum())
        mse = float(err[:, cols].sum() / count) if count else math.nan
        baseline = float(base[:, cols].sum() / count) if count else math.nan
        out[group] = {"mse": round(mse, 4), "baseline": round(baseline, 4),
                      "ratio": round(mse / baseline, 4) if count and baseline > 0 else math.nan, "count": int(count)}
    return out


def _predict(net, frames: np.ndarray, batch: int = 256) -> np.ndarray:
    import torch

    net.eval()
    out = []
    with torch.no_grad():
        for start in range(0, len(frames), batch):
            out.append(net(torch.as_tensor(frames[start:start + batch]))[1].numpy())
    return np.concatenate(out) if out else np.zeros((0, net.head.out_features), np.float32)


def fit(data: EncoderData, epochs: int = 5, batch_size: int = 128, lr: float = 5e-4, seed: int = 0,
        progress: bool = False):
    """Train an :class:`agents.encoder.EncoderNet` on ``data``'s training frames (module
    docstring); returns ``(net, mean, std, history)``, ``history`` the training loss per epoch."""
    import torch
    from tqdm import tqdm

    from agents.encoder import EncoderNet

    torch.manual_seed(seed)
    train = np.flatnonzero(~data.held_out)
    if len(train) == 0:
        raise TrainError("no training frames: give --frames larger than the held-out share")
    labels = data.labels
    mean, std = normalisation(labels[train], label_weights(labels[train]))
    net = EncoderNet(data.frames.shape[1:], labels.shape[1])
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    rng = np.random.default_rng(seed)
    steps = epochs * math.ceil(len(train) / batch_size)
    bar = tqdm(total=steps, unit="batch", desc="encoder training", disable=not progress, dynamic_ncols=True)
    history = []
    mean_t, std_t = torch.as_tensor(mean), torch.as_tensor(std)
    try:
        for _ in range(epochs):
            net.train()
            order = rng.permutation(train)
            total, count = 0.0, 0.0
            for start in range(0, len(order), batch_size):
                rows = np.sort(order[start:start + batch_size])
                y = torch.as_tensor(labels[rows])
                w = torch.as_tensor(label_weights(labels[rows]))
                _, pred = net(torch.as_tensor(data.frames[rows]))
                loss = (w * (pred - (y - mean_t) / std_t) ** 2).sum() / w.sum().clamp(min=1.0)
                opt.zero_grad()
                loss.backward()
                opt.step()
                total, count = total + float(loss.detach()) * len(rows), count + len(rows)
                bar.update(1)
                bar.set_postfix_str(f"loss {total / count:.3f}", refresh=False)
            history.append(round(total / max(count, 1), 4))
    finally:
        bar.close()
    return net, mean, std, history


def build(out: Path, frames: int = 40_000, epochs: int = 5, seed: int = 0, envs: Sequence[str] | None = None,
          agents: int | None = None, obs: str = "image", horizon: int = 200, held_out: float = 0.1,
          batch_size: int = 128, lr: float = 5e-4, data: Path | None = None, progress: bool = False,
          command: str | None = None) -> dict[str, Any]:
    """Collect (or read ``data``, an .npz :func:`collect` wrote; written there when missing),
    train and save an encoder to ``out``; returns its summary (also in the file's ``info``):
    sizes, times, training loss and held-out error per group (:func:`group_errors`)."""
    from agents.encoder import save_encoder
    from eval.labels import ENVS
    from eval.training.runfolder import software

    envs = tuple(envs or ENVS)
    if obs not in camera_variants():
        raise TrainError(f"--obs {obs}: an encoder takes camera frames; use one of {', '.join(camera_variants())}")
    start = time.monotonic()
    if data is not None and Path(data).is_file():
        dataset = EncoderData.load(Path(data))
    else:
        dataset = collect(envs, frames, seed, agents, obs, horizon, held_out, progress=progress)
        if data is not None:
            dataset.save(Path(data))
    collected = time.monotonic()
    net, mean, std, history = fit(dataset, epochs, batch_size, lr, seed, progress)
    trained = time.monotonic()
    held = np.flatnonzero(dataset.held_out)
    predicted = _predict(net, dataset.frames[held]) * std + mean  # the head predicts normalised labels
    errors = group_errors(predicted, dataset.labels[held], mean, std) if len(held) else {}
    info = {"frames": len(dataset.frames), "train_frames": int((~dataset.held_out).sum()), "held_out_frames": len(held),
            "envs": list(dataset.envs), "agents": agents, "obs": obs, "horizon": horizon, "seed": seed,
            "epochs": epochs, "batch_size": batch_size, "lr": lr, "data_bytes": dataset.nbytes,
            "collect_seconds": round(collected - start, 1), "train_seconds": round(trained - collected, 1),
            "train_loss": history, "held_out_error": errors, "software": software(command)}
    info["sha256"] = save_encoder(out, net, labels=label_names(), mean=mean, std=std, obs=obs, info=info)
    return info


@functools.lru_cache(maxsize=4)
def _load(path: str, sha256: str | None, threads: int | None):
    from agents.encoder import load_encoder

    return load_encoder(path, sha256, threads)


def run_encoder(cfg: TrainConfig, threads: int | None = None):
    """The frozen encoder of a run (``cfg.encoder``, checked against ``cfg.encoder_sha256``), or
    None without one; loaded once per process and file.

    Raises:
        TrainError: the file is missing, not an encoder, of another hash than the run's, trained
            on another camera variant than ``cfg.obs`` or another camera size.
    """
    if cfg.encoder is None:
        return None
    from agents.encoder import EncoderError

    try:
        encoder = _load(cfg.encoder, cfg.encoder_sha256, threads)
    except EncoderError as exc:
        raise TrainError(f"--encoder: {exc}") from None
    if encoder.obs != cfg.obs:
        raise TrainError(f"--encoder {cfg.encoder} was trained on {encoder.obs} frames, the run observes "
                         f"--obs {cfg.obs}: use --obs {encoder.obs}, or build an encoder on them "
                         f"(`cosim encoder train --obs {cfg.obs}`)")
    if encoder.image_shape[:2] != (cfg.image_size, cfg.image_size):
        raise TrainError(f"--encoder {cfg.encoder} takes {encoder.image_shape[0]}-pixel frames, the run's camera "
                         f"gives {cfg.image_size}; build an encoder for them")
    return encoder


def observation(env, cfg: TrainConfig, threads: int | None = None):
    """``env`` (a cosim env) with the observation a run of ``cfg`` trains on: as
    cosim.wrappers.observation_wrappers builds it, or with ``cfg.encoder`` each AC's last
    ``frame_stack`` feature vectors of the frozen encoder (module docstring). ``threads``: the
    encoder's torch threads (None: the process's)."""
    from cosim.wrappers import FrameStack, observation_wrappers

    repeat = cfg.agent_config.action_repeat
    encoder = run_encoder(cfg, threads)
    if encoder is None:
        return observation_wrappers(env, frame_stack=cfg.frame_stack, obs=cfg.obs, action_repeat=repeat)
    from agents.encoder import EncodedObservation

    env = EncodedObservation(observation_wrappers(env, frame_stack=1, obs=cfg.obs, action_repeat=repeat), encoder)
    return FrameStack(env, cfg.frame_stack) if cfg.frame_stack > 1 else env
