"""Self-describing agent checkpoints.

One file (``torch.save``) holds everything needed to rebuild an agent without
knowing how it was trained::

    {
      "format": "cosim-agents-checkpoint", "format_version": 1,
      "algo": "ppo", "config": {...dataclasses.asdict(config)...},
      "observation_space": {"type": "Box", ...},  # or {"type": "Dict", "spaces": {"image": ..., ...}}
      "action_space": {"type": "Discrete", ...},
      "state": agent.state_dict(),          # weights, optimizer states, counters
      "versions": {"torch": ..., "numpy": ..., "cosim-agents": ...},
    }

Spaces are plain dicts, not pickled objects, and every value is a tensor or a
plain Python value, so loading uses ``torch.load(weights_only=True)``: a
checkpoint cannot run code on the machine that loads it.

Every file carries ``"checksum"``: the SHA-256 of its contents (every tensor's bytes, every
value; :func:`content_digest`), checked at load, so a file changed after it was saved (a
flipped byte on disk, a partial copy) is refused as corrupt rather than loaded with altered
weights (files written before the checksum load unchecked). A save is atomic: the bytes go to
``<name>.tmp`` (fsync'ed), then renamed; a failed write (a full disk) removes the ``.tmp``,
leaves any previous file under the name as it was and raises :class:`CheckpointError`.

Two kinds (``"kind"`` in the payload): a *full* checkpoint holds every network,
optimizer state and counter, all that resuming training needs; a *policy*
checkpoint (``save_checkpoint(..., policy_only=True)``) holds only the networks
that choose actions (``agents.registry.POLICY_NETWORKS``: no optimizer moments,
no target networks; DDPG/TD3 keep the critic whose CNN their actor acts on) and the
counters, 1/3 to 1/5 of the size (its weights byte-shuffled and zlib'ed, lossless: ~85% of
float32). A policy checkpoint loads into an agent that acts exactly as the full one would;
its ``policy_only`` attribute is True and training it is refused where a loader asks for a
full checkpoint (``require_full=True``). Weights are stored as float32 unless a policy file
is asked for float16 (``policy_dtype``, :data:`POLICY_DTYPES`: half the bytes, rounded, so
its actions can differ; the ``smoke`` run preset's choice); a full checkpoint is always
float32.
"""

from __future__ import annotations

import errno
import hashlib
import importlib.metadata
import io
import logging
import os
import shutil
import zlib
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch

from agents.errors import AgentError
from agents.registry import POLICY_DTYPES

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "CheckpointError",
    "content_digest",
    "load_checkpoint",
    "POLICY_DTYPES",
    "policy_state",
    "retune_checkpoint",
    "save_checkpoint",
    "space_from_dict",
    "space_to_dict",
    "warm_start",
]

logger = logging.getLogger(__name__)

FORMAT = "cosim-agents-checkpoint"
FORMAT_VERSION = 1


class CheckpointError(AgentError):
    """A checkpoint file is missing, unreadable, of another format or another algorithm."""


def _feed(h, obj) -> None:
    """Feed ``obj`` (a checkpoint payload's value) into the hash ``h``, type-tagged."""
    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)};".encode())
        if t.numel():
            h.update(memoryview(t.reshape(-1).view(torch.uint8).numpy()))
    elif isinstance(obj, dict):
        h.update(f"D{len(obj)};".encode())
        for key in sorted(obj, key=repr):
            _feed(h, key)
            _feed(h, obj[key])
    elif isinstance(obj, (list, tuple)):  # a tuple may come back a list: the same digest
        h.update(f"L{len(obj)};".encode())
        for item in obj:
            _feed(h, item)
    elif isinstance(obj, (bytes, bytearray)):
        h.update(f"B{len(obj)};".encode())
        h.update(obj)
    else:  # str, bool, int, float, None: their repr is what they load back as
        text = repr(obj).encode()
        h.update(f"{type(obj).__name__}{len(text)};".encode())
        h.update(text)


def content_digest(payload: dict[str, Any]) -> str:
    """The SHA-256 (hex) of a checkpoint payload's contents without its ``"checksum"``: what
    :func:`save_checkpoint` stores and :func:`load_checkpoint` checks (module docstring)."""
    h = hashlib.sha256()
    _feed(h, {k: v for k, v in payload.items() if k != "checksum"})
    return h.hexdigest()


def _write(payload: dict[str, Any], path: Path) -> None:
    """``payload`` with its checksum, to ``path`` atomically (module docstring).

    Raises:
        CheckpointError: the file could not be written (a full disk, a read-only folder),
            naming the file, the reason and the free space.
    """
    payload = {**payload, "checksum": content_digest(payload)}
    buffer = io.BytesIO()
    torch.save(payload, buffer)  # in memory: a full disk is an OSError of the write below
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(buffer.getbuffer())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        try:
            free = f"{shutil.disk_usage(path.parent).free / 1e6:.1f} MB free there"
        except OSError:
            free = "free space unknown"
        hint = "the disk is full: free space" if err.errno in (errno.ENOSPC, errno.EDQUOT) else "fix the folder"
        raise CheckpointError(
            f"cannot write checkpoint {path} ({err.strerror or err}; {len(buffer.getbuffer()) / 1e6:.1f} MB "
            f"needed, {free}); {hint}, then save again (a training run: `cosim train --resume RUN`)"
        ) from err


def _library_version() -> str:
    try:
        return importlib.metadata.version("cosim")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _compact(array: np.ndarray):
    """A scalar when every element is equal (image bounds), else a nested list."""
    flat = array.reshape(-1)
    if flat.size and np.all(flat == flat[0]):
        return flat[0].item()
    return array.tolist()


def space_to_dict(space: gymnasium.Space) -> dict[str, Any]:
    """Serialise a Box or Discrete space, or a Dict of them (cosim's ``obs="nav"`` observation:
    ``Dict(image, measurements)``), to a plain dict. The observation space's format (Box or
    Dict) is what an agent loaded from it checks its observations against
    (agents/base.py check_variant).

    Raises:
        ValueError: For other space types.
    """
    if isinstance(space, gymnasium.spaces.Discrete):
        return {"type": "Discrete", "n": int(space.n), "start": int(space.start)}
    if isinstance(space, gymnasium.spaces.Box):
        return {
            "type": "Box",
            "shape": tuple(int(d) for d in space.shape),
            "dtype": np.dtype(space.dtype).name,
            "low": _compact(space.low),
            "high": _compact(space.high),
        }
    if isinstance(space, gymnasium.spaces.Dict):
        return {"type": "Dict", "spaces": {key: space_to_dict(sub) for key, sub in space.spaces.items()}}
    raise ValueError(f"checkpoints support Box, Discrete and Dict spaces, got {space!r}")


def space_from_dict(data: dict[str, Any]) -> gymnasium.Space:
    """Rebuild a space written by :func:`space_to_dict`."""
    if data["type"] == "Discrete":
        return gymnasium.spaces.Discrete(data["n"], start=data.get("start", 0))
    if data["type"] == "Box":
        dtype = np.dtype(data["dtype"])
        shape = tuple(data["shape"])
        low = np.broadcast_to(np.asarray(data["low"], dtype=dtype), shape)
        high = np.broadcast_to(np.asarray(data["high"], dtype=dtype), shape)
        return gymnasium.spaces.Box(low=low, high=high, shape=shape, dtype=dtype)
    if data["type"] == "Dict":
        return gymnasium.spaces.Dict({key: space_from_dict(sub) for key, sub in data["spaces"].items()})
    raise ValueError(f"unknown space type {data['type']!r}")


def pack_tensor(tensor: torch.Tensor, dtype: str = "float32") -> dict[str, Any]:
    """A tensor compressed: its bytes grouped by significance (byte shuffle, as Blosc and HDF5
    do: the exponent bytes of float weights are alike) and zlib'ed. Trained float32 weights
    shrink to ~85%; :func:`unpack_tensor` gives the same bits back. ``dtype`` "float16" first
    rounds float32 weights to float16 (lossy; :data:`POLICY_DTYPES`) and records the dtype
    that :func:`unpack_tensor` restores."""
    array = tensor.detach().cpu().contiguous().numpy()
    cast_from = None
    if dtype == "float16" and array.dtype == np.float32:
        cast_from, array = array.dtype.str, array.astype(np.float16)
    shuffled = array.reshape(-1).view(np.uint8).reshape(-1, array.itemsize).T.tobytes()
    data = torch.frombuffer(bytearray(zlib.compress(shuffled, 6)), dtype=torch.uint8)
    packed = {"packed": "shuffle-zlib", "dtype": array.dtype.str, "shape": list(array.shape), "data": data}
    if cast_from is not None:
        packed["cast_from"] = cast_from
    return packed


def unpack_tensor(packed: dict[str, Any]) -> torch.Tensor:
    """The tensor :func:`pack_tensor` packed, bit for bit (float16-stored weights come back
    as the float32 values of their float16 rounding)."""
    dtype = np.dtype(packed["dtype"])
    raw = np.frombuffer(zlib.decompress(packed["data"].numpy().tobytes()), dtype=np.uint8)
    array = raw.reshape(dtype.itemsize, -1).T.copy().view(dtype).reshape(packed["shape"])
    if "cast_from" in packed:
        array = array.astype(np.dtype(packed["cast_from"]))
    return torch.from_numpy(array)


def policy_state(agent, dtype: str = "float32") -> dict[str, Any]:
    """The part of ``agent.state_dict()`` that acting needs: the policy networks (packed,
    :func:`pack_tensor`, float weights as ``dtype``) and counters."""
    from agents.registry import POLICY_NETWORKS

    state = agent.state_dict()
    keep = POLICY_NETWORKS[agent.algo]
    return {"networks": {k: {name: pack_tensor(t, dtype) for name, t in v.items()}
                         for k, v in state["networks"].items() if k in keep},
            "optimizers": {}, "extra": state.get("extra", {})}


def save_checkpoint(path, agent, policy_only: bool = False, policy_dtype: str = "float32") -> None:
    """Write ``agent`` to ``path`` as one self-describing file.

    The file is written to a temporary name and renamed, so an interrupted save
    never leaves a truncated checkpoint under the final name.

    Args:
        path: Destination file (parent folders are created).
        agent: An :class:`agents.base.Agent`.
        policy_only: Keep only what acting needs (module docstring), not what
            resuming training needs.
        policy_dtype: How a policy file stores its float weights (:data:`POLICY_DTYPES`):
            "float32" (exact) or "float16" (half the bytes, rounded). A full checkpoint
            resumes training exactly, so it is always float32.

    Raises:
        ValueError: ``policy_dtype`` not one of :data:`POLICY_DTYPES`, or "float16" for a
            full checkpoint.
    """
    if policy_dtype not in POLICY_DTYPES:
        raise ValueError(f"policy_dtype must be one of {', '.join(POLICY_DTYPES)}, got {policy_dtype!r}")
    if policy_dtype != "float32" and not policy_only:
        raise ValueError("policy_dtype float16 is for policy files (policy_only=True): a full "
                         "checkpoint keeps float32 so that training resumes exactly")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": "policy" if policy_only else "full",
        "algo": agent.algo,
        "config": agent.config.to_dict(),
        "observation_space": space_to_dict(agent.observation_space),
        "action_space": space_to_dict(agent.action_space),
        "seed": agent.seed,
        "state": policy_state(agent, policy_dtype) if policy_only else agent.state_dict(),
        "versions": {
            "torch": str(torch.__version__),
            "numpy": str(np.__version__),
            "cosim-agents": _library_version(),
        },
    }
    _write(payload, path)
    logger.info("saved %s checkpoint to %s", agent.algo, path)


def _read(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist; check the path (cwd is {Path.cwd()})")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch.load of arbitrary bytes raises anything (KeyError: 101 for "h...")
        reason = " ".join(str(err).split())[:200]
        raise CheckpointError(
            f"checkpoint {path} is truncated or corrupt ({type(err).__name__}: {reason}); "
            "re-save it from the training run or use an earlier checkpoint"
        ) from err
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(
            f"{path} is not a cosim agents checkpoint (no '{FORMAT}' header); "
            "save agents with agent.save(path), not torch.save(model)"
        )
    version = payload.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"checkpoint {path} has format version {version}, this library reads version "
            f"{FORMAT_VERSION}; load it with the cosim version that wrote it "
            f"({payload.get('versions', {}).get('cosim-agents', 'unknown')})"
        )
    stored = payload.pop("checksum", None)  # None: written before checksums, loaded unchecked
    if stored is not None:
        try:
            actual = content_digest(payload)
        except Exception as err:  # a value no save writes (a corrupt file can unpickle to anything)
            actual = f"unhashable ({type(err).__name__})"
        if actual != stored:
            raise CheckpointError(
                f"checkpoint {path} is corrupt: its contents do not match the checksum saved with "
                "them (the file changed on disk after it was written); use another copy or an "
                "earlier checkpoint, or train again"
            )
    return payload


def retune_checkpoint(path, config) -> None:
    """Rewrite the checkpoint at ``path`` so that its agent goes on training with ``config``
    (same algorithm; PBT's explore step): the recorded config, and each optimizer's learning
    rate (``Agent.optimizer_learning_rates``; a loaded optimizer state would otherwise bring
    the old rate back). Weights, optimizer moments and counters are kept bit for bit; a policy
    checkpoint (no optimizers) changes its config only. Written to a temporary name and renamed.

    Raises:
        CheckpointError: not a checkpoint, or ``config`` is not its algorithm's config class.
    """
    from agents.registry import get_agent_class

    path = Path(path)
    payload = _read(path)
    cls = get_agent_class(payload["algo"])
    if not isinstance(config, cls.config_class):
        raise CheckpointError(f"checkpoint {path} holds a {payload['algo']!r} agent; retune it with a "
                              f"{cls.config_class.__name__}, not a {type(config).__name__}")
    payload["config"] = config.to_dict()
    for name, state in payload["state"].get("optimizers", {}).items():
        rate = float(getattr(config, cls.optimizer_learning_rates[name]))
        for group in state.get("param_groups", []):
            group["lr"] = rate
    _write(payload, path)


def load_checkpoint(path, device: str = "cpu", expected_algo: str | None = None,
                    require_full: bool = False):
    """Rebuild an agent from a checkpoint written by :func:`save_checkpoint`.

    Args:
        path: The checkpoint file.
        device: Torch device for the rebuilt agent.
        expected_algo: If given, the checkpoint must hold this algorithm.
        require_full: Refuse a policy checkpoint (to resume training, which needs
            the optimizer states and target networks it does not hold).

    Returns:
        The agent, with weights, optimizer states and counters restored (a policy
        checkpoint: the policy networks and counters; ``agent.policy_only`` True).

    Raises:
        CheckpointError: If the file is missing, truncated or corrupt, of another
            format or version, of another algorithm than ``expected_algo``, its
            contents do not match the algorithm's networks, or it is a policy
            checkpoint and ``require_full`` is set.
    """
    from agents.registry import POLICY_NETWORKS, get_agent_class

    path = Path(path)
    payload = _read(path)
    algo = payload.get("algo")
    policy_only = payload.get("kind", "full") == "policy"
    if policy_only and require_full:
        raise CheckpointError(
            f"checkpoint {path} holds the policy only (no optimizer states or target networks), "
            "so training cannot resume from it; resume from the run's latest.pt (kept while a run "
            "is unfinished, or with --keep all)"
        )
    if expected_algo is not None and algo != expected_algo:
        raise CheckpointError(
            f"checkpoint {path} holds a {algo!r} agent, not {expected_algo!r}; "
            f"load it with agents.load(path) or the {algo!r} agent class"
        )
    try:
        cls = get_agent_class(algo)
    except KeyError as err:
        raise CheckpointError(f"checkpoint {path}: {err.args[0]}") from None
    try:
        config = cls.config_class.from_dict(payload["config"])
        agent = cls(
            space_from_dict(payload["observation_space"]),
            space_from_dict(payload["action_space"]),
            config=config,
            seed=payload.get("seed", 0),
            device=device,
        )
        if policy_only:
            state = payload["state"]
            missing = sorted(set(POLICY_NETWORKS[algo]) - set(state["networks"]))
            if missing:
                raise KeyError(f"policy checkpoint has no weights for network(s) {missing}")
            for name in POLICY_NETWORKS[algo]:
                agent.networks[name].load_state_dict(
                    {k: unpack_tensor(v) if isinstance(v, dict) else v for k, v in state["networks"][name].items()})
            agent._load_extra_state(state.get("extra", {}))
        else:
            agent.load_state_dict(payload["state"])
        agent.policy_only = policy_only
    except CheckpointError:
        raise
    except Exception as err:  # KeyError, ValueError, TypeError, RuntimeError, zlib.error, ...
        raise CheckpointError(
            f"checkpoint {path} ({algo}) does not match this library's {cls.__name__}: "
            f"{type(err).__name__}: {' '.join(str(err).split())[:300]}; it was written by versions "
            f"{payload.get('versions')}"
        ) from err
    logger.info("loaded %s checkpoint from %s", algo, path)
    return agent


def warm_start(agent, path) -> None:
    """Start ``agent`` from the policy weights of the checkpoint at ``path`` (full or policy):
    its policy networks (``agents.registry.POLICY_NETWORKS``) are copied in and its target
    networks set to copies of them (``TARGET_NETWORKS``); its optimizer states, counters and
    schedules (epsilon, learning starts, noise) stay those of a fresh agent, so the warm-started
    run explores and learns as a new run of its own config would, from these weights
    (``cosim train --init-from``, docs/agents.md "Warm start").

    Raises:
        CheckpointError: unreadable, another algorithm, or other observation or action spaces
            than ``agent``'s (naming both).
    """
    from agents.registry import POLICY_NETWORKS, TARGET_NETWORKS

    path = Path(path)
    source = load_checkpoint(path, expected_algo=agent.algo)
    for what in ("observation_space", "action_space"):
        theirs, ours = space_to_dict(getattr(source, what)), space_to_dict(getattr(agent, what))
        if theirs != ours:
            raise CheckpointError(f"checkpoint {path} was trained with {what} {getattr(source, what)}, "
                                  f"this run has {getattr(agent, what)}; warm-start from a run with "
                                  "the same --obs, --frame-stack and action type")
    for name in POLICY_NETWORKS[agent.algo]:
        agent.networks[name].load_state_dict(source.networks[name].state_dict())
    for target, online in TARGET_NETWORKS[agent.algo].items():
        agent.networks[target].load_state_dict(agent.networks[online].state_dict())
    logger.info("warm-started %s from %s", agent.algo, path)
