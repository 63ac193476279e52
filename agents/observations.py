"""The two observation formats the agents take, and batches of either.

An observation is an image (a Box), or an image beside a measurements vector:
``Dict(image, measurements)`` (:func:`is_nav_space`; cosim's ``obs="nav"``, docs/task.md,
"Observation").

Buffers, unrolls and the vector env's per-agent rows hold a batch of observations with the
batch on the first axis: one ``(N, ...)`` array for a Box space, or ``{"image": (N, H, W, C),
"measurements": (N, M)}`` for a Dict space. The functions here do to either what numpy does to
an array (index, assign, stack, concatenate, compare, copy), key by key for a dict, so the code
that stores and moves observations is the same for both; on arrays they are the plain numpy
operations. Only numpy and Gymnasium spaces: the vector env's workers import this.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import gymnasium
import numpy as np

__all__ = ["NAV_KEYS", "asarray", "assign", "concatenate", "copy", "equal", "image_space", "is_nav_space", "join",
           "parts", "put", "stack", "take", "zeros"]


NAV_KEYS = ("image", "measurements")
"""The keys of an image-and-measurements observation (cosim's ``obs="nav"``)."""


def is_nav_space(observation_space) -> bool:
    """``Dict(image=<(H, W, C) Box>, measurements=<(M,) Box>)``: an image with measurements."""
    return (isinstance(observation_space, gymnasium.spaces.Dict)
            and tuple(sorted(observation_space.spaces)) == NAV_KEYS
            and len(observation_space["image"].shape) == 3 and len(observation_space["measurements"].shape) == 1)


def image_space(observation_space):
    """The image part of an observation space: the space itself, or its ``image`` for
    ``Dict(image, measurements)``."""
    return observation_space["image"] if is_nav_space(observation_space) else observation_space


def parts(space) -> dict[str, gymnasium.spaces.Box]:
    """The arrays an observation of ``space`` is made of: ``{"": space}`` for a Box, the
    sub-spaces (in the space's key order) for a Dict."""
    if isinstance(space, gymnasium.spaces.Dict):
        return dict(space.spaces)
    return {"": space}


def join(arrays: Mapping[str, np.ndarray]):
    """The inverse of :func:`parts` for arrays: ``{"": array}`` -> the array, else the dict."""
    return arrays[""] if "" in arrays else dict(arrays)


def zeros(space, n: int, dtype=None):
    """A zero batch of ``n`` observations of ``space`` (``dtype(sub_space)`` picks each part's
    dtype; default: the space's own)."""
    return join({key: np.zeros((n, *sub.shape), sub.dtype if dtype is None else dtype(sub))
                 for key, sub in parts(space).items()})


def take(batch, index):
    """``batch[index]`` (rows of a numpy array or a torch tensor), key by key for a dict."""
    if isinstance(batch, Mapping):
        return {key: value[index] for key, value in batch.items()}
    return batch[index]


def put(batch, index, value) -> None:
    """``batch[index] = value``, key by key for a dict."""
    if isinstance(batch, Mapping):
        for key, part in batch.items():
            part[index] = value[key]
    else:
        batch[index] = value


def assign(target, value) -> None:
    """Write ``value`` into the array(s) ``target`` in place (``target[...] = value``)."""
    put(target, Ellipsis, value)


def stack(items: Sequence):
    """``np.stack(items)``: one batch of single observations."""
    if items and isinstance(items[0], Mapping):
        return {key: np.stack([item[key] for item in items]) for key in items[0]}
    return np.stack(items)


def concatenate(items: Sequence):
    """``np.concatenate(items)``: one batch of batches."""
    if items and isinstance(items[0], Mapping):
        return {key: np.concatenate([item[key] for item in items]) for key in items[0]}
    return np.concatenate(items)


def equal(a, b) -> bool:
    """``np.array_equal(a, b)``; dicts are equal when they have the same keys and equal arrays."""
    if isinstance(a, Mapping) or isinstance(b, Mapping):
        return (isinstance(a, Mapping) and isinstance(b, Mapping) and a.keys() == b.keys()
                and all(np.array_equal(a[key], b[key]) for key in a))
    return np.array_equal(a, b)


def copy(obs):
    """A copy of an observation (or batch) that owns its memory (``np.array(obs, copy=True)``)."""
    if isinstance(obs, Mapping):
        return {key: np.array(value, copy=True) for key, value in obs.items()}
    return np.array(obs, copy=True)


def rows(batch) -> int:
    """The number of rows of a batch (of its first array, for a dict)."""
    if isinstance(batch, Mapping):
        batch = next(iter(batch.values()))
    return len(batch)


def asarray(obs):
    """``np.asarray(obs)``, key by key for a dict."""
    if isinstance(obs, Mapping):
        return {key: np.asarray(value) for key, value in obs.items()}
    return np.asarray(obs)
