"""Experience storage: an on-policy rollout buffer and a memory-sane replay buffer.

:class:`RolloutBuffer` holds one rollout of a single agent for PPO-style
learners. :class:`ReplayBuffer` holds off-policy transitions for DQN, DDPG and
TD3; it keeps observations in their own dtype (uint8 for images) and stores
each observation ONCE: ``next_obs`` of transition ``i`` is read from slot
``i + 1`` (the next transition's ``obs``), so a 100k-transition buffer of
84x84x3 images takes ~2.1 GB instead of ~4.2 GB (SB3's
``optimize_memory_usage`` idea). The only exception is a truncated episode,
whose final observation is kept on the side because the next slot holds the
first observation of the following episode.

Both take transitions from several environments at once (``agents/vector.py``):
each transition carries its environment index (``column``). The rollout
buffer keeps one flat list and bootstraps and computes advantages per column;
the replay buffer splits its capacity into one ring per column, so the
"next observation is the next slot" rule holds inside each ring.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium
import numpy as np
import torch

from agents import observations
from agents.networks import obs_to_tensor
from agents.observations import image_space, is_nav_space

__all__ = ["FRAME_CHANNELS", "ReplayBuffer", "ReplaySample", "RolloutBuffer", "frames_in"]


def _obs_dtype(space: gymnasium.spaces.Box) -> np.dtype:
    return np.uint8 if space.dtype == np.uint8 else np.float32


def _obs_zeros(space, n: int):
    """``n`` zero observations of ``space`` as stored: uint8 images stay uint8, the rest float32
    (a dict of such arrays for ``Dict(image, measurements)``; agents/observations.py)."""
    return observations.zeros(space, n, _obs_dtype)


class RolloutBuffer:
    """Fixed-length time-major storage for one on-policy rollout of one agent.

    Args:
        size: Number of transitions per rollout.
        observation_space: Space of one observation.
        action_shape: Shape of one action (``()`` for Discrete).
        action_dtype: numpy dtype of the actions.
        n_logits: Width of the stored policy logits (0 to skip them).

    ``full`` once ``size`` transitions are stored; :meth:`ensure_capacity` lets a
    batch from several environments run past ``size`` (the learner takes them all).
    """

    def __init__(self, size: int, observation_space, action_shape=(), action_dtype=np.int64, n_logits: int = 0):
        if size < 1:
            raise ValueError(f"RolloutBuffer size must be >= 1, got {size}")
        self.size = size
        self.obs = _obs_zeros(observation_space, size)
        """The observations: an array, or a dict of arrays for a Dict(image, measurements) space."""
        self.actions = np.zeros((size, *action_shape), action_dtype)
        self.log_probs = np.zeros(size, np.float32)
        self.logits = np.zeros((size, n_logits), np.float32)
        self.values = np.zeros(size, np.float32)
        self.rewards = np.zeros(size, np.float32)
        self.terminateds = np.zeros(size, bool)
        self.truncateds = np.zeros(size, bool)
        # Value of the observation that followed step t; filled where it is not values[t + 1].
        self.next_values = np.zeros(size, np.float32)
        self.columns = np.zeros(size, np.int64)  # environment index of each transition
        self.pos = 0

    @property
    def capacity(self) -> int:
        """Transitions the arrays can hold now (``size`` unless grown)."""
        return len(self.rewards)

    def ensure_capacity(self, n: int) -> None:
        """Grow the arrays so that ``n`` transitions fit (a batch of N envs past ``size``)."""
        if n <= self.capacity:
            return

        def grown(old: np.ndarray) -> np.ndarray:
            new = np.zeros((n, *old.shape[1:]), old.dtype)
            new[: len(old)] = old
            return new

        for name in ("actions", "log_probs", "logits", "values", "rewards", "terminateds", "truncateds",
                     "next_values", "columns"):
            setattr(self, name, grown(getattr(self, name)))
        obs = self.obs
        self.obs = {key: grown(part) for key, part in obs.items()} if isinstance(obs, dict) else grown(obs)

    @property
    def full(self) -> bool:
        """True once ``size`` transitions are stored."""
        return self.pos >= self.size

    def add(self, obs, action, log_prob, value, reward, terminated, truncated, logits=None, column: int = 0) -> int:
        """Append one transition of environment ``column``; returns its index.

        Raises:
            RuntimeError: If the buffer is already full (call ``reset`` after learning).
        """
        if self.pos >= self.capacity:
            raise RuntimeError("RolloutBuffer is full; learn from it and call reset() first")
        t = self.pos
        observations.put(self.obs, t, obs)
        self.actions[t] = action
        self.log_probs[t] = log_prob
        self.values[t] = value
        self.rewards[t] = reward
        self.terminateds[t] = terminated
        self.truncateds[t] = truncated
        if logits is not None:
            self.logits[t] = logits
        self.columns[t] = column
        self.pos += 1
        return t

    def bootstrap_values(self, last_next_value: float) -> np.ndarray:
        """Fill ``next_values`` inside episodes from ``values[t + 1]``; the last step gets ``last_next_value``.

        Steps that ended an episode keep what was written into ``next_values`` when
        they were observed (the final observation's value for a truncation; ignored
        for a termination).
        """
        return self.bootstrap_columns(dict.fromkeys(np.unique(self.columns[: self.pos]).tolist(), last_next_value))

    def bootstrap_columns(self, last_next_values) -> np.ndarray:
        """:meth:`bootstrap_values` per environment: inside each column's sequence of
        transitions ``next_values`` is the next one's value; each column's last
        transition, if its episode goes on, gets ``last_next_values[column]``.

        Returns:
            ``next_values`` of the ``pos`` stored transitions.
        """
        n = self.pos
        ended = (self.terminateds | self.truncateds)[:n]
        for column in np.unique(self.columns[:n]):
            idx = np.flatnonzero(self.columns[:n] == column)
            inside = ~ended[idx[:-1]]
            self.next_values[idx[:-1][inside]] = self.values[idx[1:][inside]]
            if not ended[idx[-1]]:
                self.next_values[idx[-1]] = last_next_values[int(column)]
        return self.next_values[:n]

    def column_indices(self) -> list[np.ndarray]:
        """Indices of each environment's transitions, in time order (GAE runs per column)."""
        columns = self.columns[: self.pos]
        return [np.flatnonzero(columns == c) for c in np.unique(columns)]

    def reset(self) -> None:
        """Start a new rollout (the arrays are reused)."""
        self.pos = 0
        self.next_values[:] = 0.0


@dataclass
class ReplaySample:
    """A minibatch of transitions as tensors (observations keep their stored dtype)."""

    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_obs: torch.Tensor
    terminateds: torch.Tensor
    demos: torch.Tensor | None = None
    """True where the transition is a demonstration (:meth:`ReplayBuffer.add` with ``demo``)."""
    discounts: torch.Tensor | None = None
    """With ``n_step`` > 1: each row's discount of its bootstrap, gamma ** (steps it spans);
    None for 1-step samples (the discount is the learner's gamma)."""


FRAME_CHANNELS = 3
"""Channels of one camera frame (RGB): a uint8 image of 3K channels is K stacked frames."""


def frames_in(space) -> int:
    """How many camera frames an observation space stacks (cosim.wrappers.FrameStack): K for
    a uint8 (H, W, 3K) image (alone or in ``Dict(image, measurements)``), else 1
    (docs/task.md, "Observation")."""
    space = image_space(space)
    shape = getattr(space, "shape", None) or ()
    if getattr(space, "dtype", None) != np.uint8 or len(shape) != 3:
        return 1
    channels = shape[-1]
    return channels // FRAME_CHANNELS if channels % FRAME_CHANNELS == 0 else 1


class ReplayBuffer:
    """Circular replay buffer of one agent's transitions, each observation stored once.

    Transitions of one column (one environment) must be added in the order they
    happened (what one agent in ``run_loop`` does): while an episode continues,
    ``obs`` of a transition is the ``next_obs`` of the one before it. Once a
    column's ring is full, all but its oldest transition are sampled: the oldest
    slot already holds the newest ``next_obs``.

    Frame stacks are stored one frame per slot. With observations of K stacked frames
    (``frame_stack``; by default read from the space, :func:`frames_in`), each slot keeps
    only its newest frame and a sample rebuilds the K-frame stack from the slots before it,
    back to the start of its episode (where the stack repeats its first frame, as
    cosim.wrappers.FrameStack does), so the buffer takes the memory of single frames
    (the DQN recipe of Mnih et al. 2015). An episode start whose stack is not K copies of one
    frame keeps its whole stack on the side; a ring that is full leaves its K-1 oldest
    slots unsampled (their history is overwritten). Observations that are not such a stack
    (the older frames of ``next_obs`` are not the newer frames of ``obs``) are refused.

    With a ``Dict(image, measurements)`` space (cosim's ``obs="nav"``) the image is stored as
    above and each slot also keeps its observation's measurements vector (a few floats), so a
    sample's measurements are those of the same transition's image; observations go in and
    come out as dicts.

    Args:
        capacity: Maximum number of transitions kept (split evenly between columns).
        observation_space: Space of one observation (uint8 images stay uint8).
        action_space: Discrete or Box space of one action.
        seed: Seed of the sampling generator.
        columns: Number of environments feeding the buffer (one ring each).
        frame_stack: Frames per observation (None: :func:`frames_in` of the space).
    """

    def __init__(self, capacity: int, observation_space, action_space, seed: int = 0, columns: int = 1,
                 frame_stack: int | None = None):
        if columns < 1:
            raise ValueError(f"ReplayBuffer columns must be >= 1, got {columns}")
        if capacity // columns < 2:
            raise ValueError(f"ReplayBuffer capacity must be >= 2 per column, got {capacity} for {columns} column(s)")
        self.nav = is_nav_space(observation_space)
        """Observations are dicts of an image and a measurements vector."""
        image = image_space(observation_space)
        self.k = frames_in(image) if frame_stack is None else int(frame_stack)
        shape = tuple(image.shape)
        divides = self.k == 1 or (bool(shape) and self.k >= 1 and shape[-1] % self.k == 0)
        if not divides:
            raise ValueError(f"frame_stack={frame_stack} does not divide the observation's last axis "
                             f"{shape}; pass frame_stack=1 for observations that are not frame stacks")
        if capacity // columns < self.k + 1:
            raise ValueError(f"ReplayBuffer capacity must be >= {self.k + 1} per column for "
                             f"{self.k}-frame stacks, got {capacity} for {columns} column(s)")
        self.columns = columns
        self.ring = capacity // columns
        self.capacity = capacity = self.ring * columns
        self.obs_shape = shape
        self.channels = shape[-1] // self.k if shape else 0
        """Channels of one stored frame (the whole observation when ``k`` is 1)."""
        frame = (*shape[:-1], self.channels) if shape else ()
        self.obs = np.zeros((capacity, *frame), _obs_dtype(image))
        """The newest frame of each slot's image (the whole image when k = 1)."""
        self.measurements = (np.zeros((capacity, *observation_space["measurements"].shape), np.float32)
                             if self.nav else None)
        """Each slot's measurements vector (nav observations), else None."""
        if isinstance(action_space, gymnasium.spaces.Discrete):
            self.actions = np.zeros(capacity, np.int64)
        else:
            self.actions = np.zeros((capacity, *action_space.shape), np.float32)
        self.rewards = np.zeros(capacity, np.float32)
        self.terminateds = np.zeros(capacity, np.float32)
        self.truncateds = np.zeros(capacity, bool)
        self.starts = np.zeros(capacity, bool)  # the slot's observation starts an episode
        self.demos = np.zeros(capacity, bool)  # the slot's transition was demonstrated
        self.heads: dict[int, np.ndarray] = {}  # start slot -> its whole stack, when not k copies
        self.final_obs: dict[int, Any] = {}  # truncated slot -> its real next_obs
        self.positions = np.zeros(columns, np.int64)  # next slot of each ring, relative to its start
        self.sizes = np.zeros(columns, np.int64)
        self._last_next: list[Any] = [None] * columns  # each column's previous next_obs
        self.rng = np.random.default_rng(seed)

    @property
    def size(self) -> int:
        """Transitions stored, over all columns."""
        return int(self.sizes.sum())

    @property
    def pos(self) -> int:
        """Next slot of column 0 (the only one for a single environment)."""
        return int(self.positions[0])

    @property
    def nbytes(self) -> int:
        """Bytes of the stored observations (what dominates the buffer's memory)."""
        return int(self.obs.nbytes) + (int(self.measurements.nbytes) if self.nav else 0)

    def __len__(self) -> int:
        return self.size

    def add(self, obs, action, reward: float, next_obs, terminated: bool, truncated: bool, column: int = 0,
            demo: bool = False) -> None:
        """Store one transition of environment ``column``; ``demo`` marks a demonstrated one
        (a scripted driver's, Agent.observe_demonstration), which samples flag in ``demos``.

        Raises:
            ValueError: with ``k`` > 1 frames, ``next_obs`` is not ``obs`` shifted by one frame.
        """
        base, j = column * self.ring, int(self.positions[column])
        i, after = base + j, base + (j + 1) % self.ring
        obs, next_obs = observations.asarray(obs), observations.asarray(next_obs)
        previous = self._last_next[column]
        start = previous is None or not observations.equal(previous, obs)
        self.starts[i] = start
        self.heads.pop(i, None)
        self._store(i, after, obs, next_obs, start)
        self.starts[after] = False
        self.heads.pop(after, None)
        self.actions[i] = action
        self.rewards[i] = reward
        self.terminateds[i] = float(terminated)
        self.truncateds[i] = truncated and not terminated
        self.demos[i] = demo
        self.final_obs.pop(i, None)
        if self.truncateds[i]:
            self.final_obs[i] = self._stored_copy(next_obs)
        self._last_next[column] = None if (terminated or truncated) else observations.copy(next_obs)
        self.positions[column] = (j + 1) % self.ring
        self.sizes[column] = min(self.sizes[column] + 1, self.ring)

    def _stored_copy(self, obs):
        """A copy of a whole observation in the stored dtypes."""
        if self.nav:
            return {"image": np.array(obs["image"], dtype=self.obs.dtype, copy=True),
                    "measurements": np.array(obs["measurements"], dtype=np.float32, copy=True)}
        return np.array(obs, dtype=self.obs.dtype, copy=True)

    def _store(self, i: int, after: int, obs, next_obs, start: bool) -> None:
        """Write the observation into slot ``i`` and the next one into slot ``after`` (its newest
        frame and, for nav observations, its measurements)."""
        image, next_image = (obs["image"], next_obs["image"]) if self.nav else (obs, next_obs)
        if self.k > 1:
            c = self.channels
            if not np.array_equal(next_image[..., :-c], image[..., c:]):
                raise ValueError(
                    f"replay buffer of {self.k}-frame stacks: the older frames of next_obs are not "
                    f"the newer frames of obs, so these observations are not frame stacks; build the "
                    f"ReplayBuffer with frame_stack=1")
            if start and not all(np.array_equal(image[..., -c:], image[..., m * c:(m + 1) * c])
                                 for m in range(self.k - 1)):
                self.heads[i] = np.array(image, dtype=self.obs.dtype, copy=True)
            self.obs[i] = image[..., -c:]
            # Written now so the newest transition can be sampled; the next add() overwrites it
            # with the same frame while the episode goes on.
            self.obs[after] = next_image[..., -c:]
        else:
            self.obs[i] = image
            self.obs[after] = next_image
        if self.nav:  # the same slots: slot i's measurements belong to slot i's image
            self.measurements[i] = obs["measurements"]
            self.measurements[after] = next_obs["measurements"]

    def _stacks(self, slots: np.ndarray, column: np.ndarray) -> np.ndarray:
        """The whole observations of ``slots`` (absolute indices), rebuilt from their frames."""
        if self.k == 1:
            return self.obs[slots]
        k, c = self.k, self.channels
        out = np.empty((len(slots), *self.obs_shape), self.obs.dtype)
        cur = slots.copy()
        out[..., (k - 1) * c:] = self.obs[cur]
        stopped = self.starts[cur].copy()
        depth = np.where(stopped, 1, k)  # frames taken from slots when the walk stopped
        base = column * self.ring
        for m in range(1, k):
            prev = base + (cur - base - 1) % self.ring
            cur = np.where(stopped, cur, prev)
            out[..., (k - 1 - m) * c:(k - m) * c] = self.obs[cur]  # a start repeats its frame
            newly = ~stopped & self.starts[cur]
            depth[newly] = m + 1
            stopped |= newly
        for row in np.flatnonzero(stopped & (depth < k)):
            head = self.heads.get(int(cur[row]))
            if head is not None:  # an episode that began with different frames: take them
                d = int(depth[row])
                out[row, ..., :(k - d) * c] = head[..., (d - 1) * c:(k - 1) * c]
        return out

    def sample(self, batch_size: int, device="cpu", n_step: int = 1, gamma: float = 1.0) -> ReplaySample:
        """Sample ``batch_size`` transitions uniformly (with replacement).

        With ``n_step`` > 1 each row spans up to ``n_step`` transitions of its episode from the
        sampled one (Sutton 1988; Rainbow's multi-step targets): its reward is their
        ``gamma``-discounted sum, its ``next_obs`` and ``terminateds`` the last one's, and
        ``discounts`` gamma ** (transitions spanned). A row stops early at its episode's end
        and at the newest transition stored; the first transition's action and ``demos`` flag
        are the row's.

        Raises:
            ValueError: If the buffer is empty.
        """
        if self.size == 0:
            raise ValueError("cannot sample from an empty ReplayBuffer")
        # A full ring's slot `pos` is its oldest transition, but its obs slot already
        # holds the newest next_obs: skip it, and the k - 1 after it whose stacks reach back there.
        full = self.sizes == self.ring
        skip = self.k  # 1 + (k - 1)
        valid = np.where(full, self.ring - skip, self.sizes)
        if self.columns == 1:  # the common case, one draw per sample
            column = np.zeros(batch_size, np.int64)
            offset = self.rng.integers(0, int(valid[0]), batch_size)
        else:
            u = self.rng.integers(0, int(valid.sum()), batch_size)
            ends = np.cumsum(valid)
            column = np.searchsorted(ends, u, side="right")
            offset = u - (ends - valid)[column]
        offset = np.where(full[column], (offset + skip + self.positions[column]) % self.ring, offset)
        idx = column * self.ring + offset
        rewards = self.rewards[idx]
        last, discounts = idx, None
        if n_step > 1:
            rewards, last, discounts = self._n_step(column, offset, n_step, gamma)
            offset = last - column * self.ring
        after = column * self.ring + (offset + 1) % self.ring
        obs = self._stacks(idx, column)
        next_obs = self._stacks(after, column)
        if self.nav:  # the measurements of the same slots as the images
            obs = {"image": obs, "measurements": self.measurements[idx]}
            next_obs = {"image": next_obs, "measurements": self.measurements[after]}
        for row in np.flatnonzero(self.truncateds[last]):
            observations.put(next_obs, row, self.final_obs[int(last[row])])
        return ReplaySample(
            obs=obs_to_tensor(obs, device),
            actions=torch.as_tensor(self.actions[idx], device=device),
            rewards=torch.as_tensor(rewards, device=device),
            next_obs=obs_to_tensor(next_obs, device),
            terminateds=torch.as_tensor(self.terminateds[last], device=device),
            demos=torch.as_tensor(self.demos[idx], device=device),
            discounts=None if discounts is None else torch.as_tensor(discounts, device=device),
        )

    def _n_step(self, column: np.ndarray, offset: np.ndarray, n_step: int, gamma: float):
        """The n-step rewards, last transitions (absolute slots) and bootstrap discounts of
        sampled transitions (:meth:`sample`)."""
        base = column * self.ring
        ahead = (self.positions[column] - 1 - offset) % self.ring  # newer transitions stored
        last = base + offset
        rewards = self.rewards[last].astype(np.float64)
        spans = np.ones(len(last), np.int64)
        going = ~(self.terminateds[last].astype(bool) | self.truncateds[last])
        for m in range(1, n_step):
            nxt = base + (offset + m) % self.ring
            going &= (ahead >= m) & ~self.starts[nxt]
            rewards = np.where(going, rewards + gamma ** m * self.rewards[nxt], rewards)
            last = np.where(going, nxt, last)
            spans += going
            going &= ~(self.terminateds[nxt].astype(bool) | self.truncateds[nxt])
        return rewards.astype(np.float32), last, (gamma ** spans).astype(np.float32)
