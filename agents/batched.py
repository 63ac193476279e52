"""Acting for several ACs in one grouped forward pass (issue 59 item 1).

Every AC has its own networks, of one architecture when the ACs run one algorithm on one
observation space. :func:`act_all` (what :func:`agents.loop.run_loop` calls once per step)
then runs ONE forward pass for all of them instead of one per AC: their observations stacked
on a leading group axis, each convolution one convolution with ``groups=G`` over their images
laid side by side on the channel axis, its weights stacked the same way; each linear layer is
each AC's own layer on a fresh copy of its slice (:func:`_layer`: a batched matrix product was
not bit for bit). Each AC then turns its own slice of the outputs into actions with
its own generators (:meth:`agents.base.Agent.act_from`), in the loop's order of ACs, so every
random stream (PPO's and A3C's sampling, DQN's epsilon, TD3's noise) draws what it drew before.

**Bit for bit.** A layer runs one grouped kernel where that kernel gives each AC's slice
exactly what the AC's own layer gives, else the AC's own kernel on its slice, decided per
layer and input shape (:class:`GroupedNetworks`); before a shape is used the whole grouped
pass is checked against each AC's own forward, and a shape that differs anywhere acts per AC.
So the actions and what learning keeps of them (PPO's log-probabilities, values and logits,
IMPALA's behaviour log-probabilities, TD3's float actions) are the per-AC forward's exactly,
and a training run gives the same weights with and without it
(tests/agents/test_batched_acting.py).

**Stacked weights follow the ACs' weights.** :class:`GroupedNetworks` keeps the stacked copy
of G ACs' modules and, before each forward, compares every stacked parameter's and buffer's
version counter and data pointer with those it copied (any in-place change bumps the counter:
an optimiser step, ``load_state_dict``, a Polyak update, a target copy; a replaced tensor or
parameter moves the pointer), re-copying only the ACs whose weights changed since: an AC that
did not learn costs nothing, one that did a copy of its stacked weights (its convolutions and
small layers: for the Nature CNN ~6% of them; measured in docs/benchmarks.md).

**Switch.** Every config's ``batched_acting`` (default True; ``--set batched_acting=false``)
keeps an AC on its own forward pass (the path before issue 59, one ``act_batch`` per AC), as
does anything :meth:`Grouper.key` cannot group: a shared-parameter slot (``--share-params``:
one network already), ACs of other classes, spaces or row counts, TD3's random phase, modules
it has no grouped form for.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from agents import observations
from agents.networks import (
    ActorCritic,
    DeterministicActor,
    DuelingQNetwork,
    ImageMeasurementsEncoder,
    MLPEncoder,
    NatureCNN,
    dueling_aggregate,
    obs_to_tensor,
    scaled_image,
)

__all__ = ["GroupedNetworks", "Grouper", "act_all", "architecture"]


# ----------------------------------------------------------------------------- the modules


_ELEMENTWISE = (nn.ReLU, nn.Tanh, nn.Identity)

# Linear layers are never stacked: each AC's own layer runs on a fresh copy of its slice. A
# batched product (torch.baddbmm on stacked weights) that gave each AC's slice exactly its own on
# the random probe of a shape still differed on real inputs (vector PPO, 2 ACs: 126 of 400
# outputs 1e-8 to 2e-7 apart), since MKL's products round with the input's alignment; the
# convolutions are most of an image network's acting cost, and they stay grouped.


def architecture(module: nn.Module) -> tuple | None:
    """A hashable description of ``module``'s layers and shapes, or None when the grouped
    forward has no form for one of its modules (then the AC acts on its own)."""
    parts = []
    for name, sub in module.named_modules():
        if isinstance(sub, nn.Linear | nn.Conv2d):
            extra = (sub.stride, sub.padding, sub.dilation, sub.groups) if isinstance(sub, nn.Conv2d) else ()
            if sub.bias is None or (isinstance(sub, nn.Conv2d) and (sub.groups != 1 or sub.padding_mode != "zeros")):
                return None
            parts.append((name, type(sub).__name__, tuple(sub.weight.shape), extra))
        elif isinstance(sub, nn.Flatten):
            if (sub.start_dim, sub.end_dim) != (1, -1):
                return None
            parts.append((name, "Flatten"))
        elif isinstance(sub, _ELEMENTWISE):
            parts.append((name, type(sub).__name__))
        elif type(sub) in _FORWARDS:
            parts.append((name, type(sub).__name__))
        else:
            return None
    for name, buffer in module.named_buffers():
        parts.append((name, "buffer", tuple(buffer.shape), str(buffer.dtype)))
    return tuple(parts)


class _Leaf:
    """One layer's weight and bias (or one buffer) in G modules, stacked, and re-copied where a
    module's tensor changed. The tensors are read from their modules at every refresh, so a
    parameter replaced by a new one is seen too (a replaced submodule is not: a new agent or
    network acts in a new group)."""

    def __init__(self, owners: Sequence[nn.Module], names: Sequence[str],
                 layout: Callable[[list[torch.Tensor]], torch.Tensor]):
        self.owners, self.names, self.layout = list(owners), list(names), layout
        groups = self._tensors()
        self.stacked = [layout([t.detach() for t in group]) for group in groups]
        self.stamps = [[_stamp(t) for t in group] for group in groups]

    def _tensors(self) -> list[list[torch.Tensor]]:
        """Per name, the G modules' tensors."""
        return [[getattr(owner, name) for owner in self.owners] for name in self.names]

    def refresh(self) -> int:
        """Copy the tensors that changed since the last copy into the stacked ones; how many."""
        copied = 0
        for i, group in enumerate(self._tensors()):
            for k, tensor in enumerate(group):
                stamp = _stamp(tensor)
                if stamp != self.stamps[i][k]:
                    with torch.no_grad():
                        self._slice(i, k, tensor).copy_(tensor.detach())
                    self.stamps[i][k] = stamp
                    copied += 1
        return copied

    def _slice(self, i: int, k: int, tensor: torch.Tensor) -> torch.Tensor:
        if self.layout is _cat:  # convolutions: the G weights one after another on the out-channel axis
            n = tensor.shape[0]
            return self.stacked[i][k * n:(k + 1) * n]
        return self.stacked[i][k]


def _stamp(tensor: torch.Tensor) -> tuple[int, int]:
    return tensor.data_ptr(), tensor._version


def _stack(tensors: list[torch.Tensor]) -> torch.Tensor:
    return torch.stack(tensors)


def _cat(tensors: list[torch.Tensor]) -> torch.Tensor:
    return torch.cat(tensors)


class GroupedNetworks:
    """The modules of G ACs of one architecture (one per AC, the same place in each AC's agent),
    evaluated for all G in one forward pass, bit for bit as each module alone.

    ``GroupedNetworks(modules)(x)`` takes an input with a leading group axis (``(G, B, ...)``,
    a dict of such for an image with measurements) and returns what ``modules[k](x[k])``
    returns for every k, stacked on that axis; or None when this input's shape has no grouped
    pass equal to the modules' own (the caller then runs each module).

    **Bit for bit.** Each layer runs one grouped kernel (a convolution with ``groups=G``, a
    batched matrix product) where that kernel gives each AC's slice exactly what the AC's own
    layer gives, else the AC's own kernel on each slice (``F.conv2d`` on the stacked weights,
    which hold the same values; linear layers always the AC's own, on a fresh copy of its slice): which one is decided per layer and input
    shape on random inputs the first time a shape comes, since BLAS and oneDNN pick their
    algorithm (and so the order of a sum) from the shapes and the CPU, never from the values.
    Before a shape is used, the whole pass is checked against the modules' own forward on a
    random input of that shape; a shape that differs anywhere is never grouped.

    Attributes:
        copies: Tensors re-copied into the stacked weights so far (after the first stacking).
        modes: (layer name, input shape) -> "grouped" or "each", as decided.
        verified: Input signature -> whether the grouped pass equals the modules' own.
    """

    def __init__(self, modules: Sequence[nn.Module]):
        keys = {architecture(m) for m in modules}
        if len(keys) != 1 or None in keys:
            raise ValueError("GroupedNetworks needs modules of one architecture it has a grouped form for")
        self.modules = list(modules)
        self.groups = len(self.modules)
        self.leaves: dict[str, _Leaf] = {}
        self.copies = 0
        self.modes: dict[tuple, str] = {}
        self.verified: dict[tuple, bool] = {}
        named = [dict(m.named_modules()) for m in self.modules]
        self.own: dict[str, list[nn.Module]] = {}  # large linear layers: each AC's own, never copied
        for name, sub in named[0].items():
            if isinstance(sub, nn.Linear):
                self.own[name] = [n[name] for n in named]
            elif isinstance(sub, nn.Conv2d):
                self.leaves[name] = _Leaf([n[name] for n in named], ("weight", "bias"),
                                          _cat if isinstance(sub, nn.Conv2d) else _stack)
        for name, _ in self.modules[0].named_buffers():
            owner, _, attr = name.rpartition(".")
            self.leaves["buffer:" + name] = _Leaf([n[owner] for n in named], (attr,), _stack)

    def refresh(self) -> int:
        """Re-copy the weights of every AC that changed since the last call; the tensors copied."""
        copied = sum(leaf.refresh() for leaf in self.leaves.values())
        self.copies += copied
        return copied

    @torch.no_grad()
    def __call__(self, x):
        self.refresh()
        signature = _signature(x)
        if signature not in self.verified:
            self.verified[signature] = self._verify(x)
        if not self.verified[signature]:
            return None
        return _forward(self, self.modules[0], "", x)

    def _verify(self, like) -> bool:
        """The grouped pass on a random input shaped as ``like`` (deciding each layer's kernel)
        equals every module's own forward on its slice, bit for bit."""
        generator = torch.Generator().manual_seed(0)
        probe = _random_like(like, generator)
        try:
            grouped = _forward(self, self.modules[0], "", probe)
        except RuntimeError:  # a kernel that refuses the grouped layout: never group this shape
            return False
        for k, module in enumerate(self.modules):
            own = module(_fresh(_slice(probe, k)))  # as an AC's own pass gets it: a tensor of its own
            if not _equal(own, _slice(grouped, k)):
                return False
        return True

    def weights(self, name: str) -> list[torch.Tensor]:
        """The stacked weight and bias of the layer ``name``."""
        return self.leaves[name].stacked

    def buffer(self, name: str) -> torch.Tensor:
        """The stacked buffer ``name`` (``(G, ...)``)."""
        return self.leaves["buffer:" + name].stacked[0]


def _signature(x) -> tuple:
    if isinstance(x, Mapping):
        return tuple((key, *_signature(value)) for key, value in sorted(x.items()))
    return tuple(x.shape), str(x.dtype), str(x.device)


def _random_like(x, generator: torch.Generator):
    """Random values of ``x``'s shape and dtype (images 0..255, floats standard normal)."""
    if isinstance(x, Mapping):
        return {key: _random_like(value, generator) for key, value in x.items()}
    if x.dtype == torch.uint8:
        return torch.randint(0, 256, x.shape, dtype=torch.uint8, generator=generator).to(x.device)
    return torch.randn(x.shape, generator=generator).to(dtype=x.dtype, device=x.device)


def _fresh(x):
    """A copy of ``x`` (a tensor or a dict of them) in memory of its own. MKL's products can
    round differently with the input's alignment, and a slice of a stacked batch starts
    wherever the slice before it ends, where an AC's own observation or activation starts
    where the allocator puts a new tensor."""
    if isinstance(x, Mapping):
        return {key: _fresh(value) for key, value in x.items()}
    return x.clone()


def _equal(a, b) -> bool:
    if isinstance(a, tuple):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b, strict=True))
    return a.shape == b.shape and bool(torch.equal(a, b))


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


# Every grouped forward below mirrors the module's own forward, with a leading group axis G:
# vectors are (G, B, D); images inside a CNN are (B, G * C, H, W), the G images side by side.


def _forward(grouped: GroupedNetworks, module: nn.Module, prefix: str, x):
    return _FORWARDS[type(module)](grouped, module, prefix, x)


def _sequential(grouped, module: nn.Sequential, prefix: str, x):
    for name, sub in module.named_children():
        x = _layer(grouped, sub, _join(prefix, name), x)
    return x


def _layer(grouped, module: nn.Module, name: str, x):
    if isinstance(module, nn.Linear):  # each AC's own layer on a fresh copy of its slice
        return torch.stack([F.linear(_fresh(x[k]), m.weight, m.bias) for k, m in enumerate(grouped.own[name])])
    if isinstance(module, nn.Conv2d):
        key = (name, tuple(x.shape))
        mode = grouped.modes.get(key)
        if mode == "grouped":
            return _grouped_kernel(grouped, module, name, x)
        each = _each_kernel(grouped, module, name, x)
        if mode is None:  # the first input of this shape (the random one of _verify): decide
            same = _equal(_grouped_kernel(grouped, module, name, x), each)
            grouped.modes[key] = "grouped" if same else "each"
        return each
    if isinstance(module, nn.Flatten):  # (B, G * C, H, W) -> (G, B, C * H * W), each image's own order
        return x.reshape(x.shape[0], grouped.groups, -1).transpose(0, 1)
    if isinstance(module, _ELEMENTWISE):
        return module(x)
    return _forward(grouped, module, name, x)


def _grouped_kernel(grouped, module, name: str, x):
    """One kernel for the G slices: a convolution with ``groups=G``, a batched matrix product."""
    weight, bias = grouped.weights(name)
    if isinstance(module, nn.Conv2d):
        return F.conv2d(x, weight, bias, module.stride, module.padding, module.dilation, grouped.groups)
    return torch.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))


def _each_kernel(grouped, module, name: str, x):
    """Each AC's own kernel on its slice, as its module computes it (a convolution's input in
    the channels-last memory that NatureCNN's permuted input and oneDNN's outputs have)."""
    weight, bias = grouped.weights(name)
    g = grouped.groups
    if isinstance(module, nn.Conv2d):
        c, out = x.shape[1] // g, weight.shape[0] // g
        outs = [F.conv2d(x[:, k * c:(k + 1) * c].contiguous(memory_format=torch.channels_last),
                         weight[k * out:(k + 1) * out], bias[k * out:(k + 1) * out],
                         module.stride, module.padding, module.dilation) for k in range(g)]
        return torch.cat(outs, dim=1)
    return torch.stack([F.linear(x[k], weight[k], bias[k]) for k in range(g)])


def _nature_cnn(grouped, module: NatureCNN, prefix: str, obs):
    g, b, h, w, c = obs.shape
    # (G, B, H, W, C) -> (B, H, W, G * C): each AC's channels side by side, then NatureCNN's own
    # conversion (channels-last memory seen as NCHW, values scaled to 0..1)
    x = scaled_image(obs.permute(1, 2, 3, 0, 4).reshape(b, h, w, g * c))
    x = _sequential(grouped, module.cnn, _join(prefix, "cnn"), x)
    return _sequential(grouped, module.linear, _join(prefix, "linear"), x)


def _mlp_encoder(grouped, module: MLPEncoder, prefix: str, obs):
    return _sequential(grouped, module.net, _join(prefix, "net"), obs.float().flatten(2))


def _image_measurements(grouped, module: ImageMeasurementsEncoder, prefix: str, obs):
    image = _nature_cnn(grouped, module.cnn, _join(prefix, "cnn"), obs["image"])
    measured = _sequential(grouped, module.mlp, _join(prefix, "mlp"), obs["measurements"].float())
    return torch.cat([image, measured], dim=-1)


def _actor_critic(grouped, module: ActorCritic, prefix: str, obs):
    features = _forward(grouped, module.encoder, _join(prefix, "encoder"), obs)
    value_features = (features if module.value_encoder is None
                      else _forward(grouped, module.value_encoder, _join(prefix, "value_encoder"), obs))
    logits = _layer(grouped, module.policy_head, _join(prefix, "policy_head"), features)
    return logits, _layer(grouped, module.value_head, _join(prefix, "value_head"), value_features).squeeze(-1)


def _dueling(grouped, module: DuelingQNetwork, prefix: str, obs):
    features = _forward(grouped, module.encoder, _join(prefix, "encoder"), obs)
    return dueling_aggregate(_layer(grouped, module.value_head, _join(prefix, "value_head"), features),
                             _layer(grouped, module.advantage_head, _join(prefix, "advantage_head"), features))


def _actor(grouped, module: DeterministicActor, prefix: str, features):
    pre = _layer(grouped, module.mu, _join(prefix, "mu"), _forward(grouped, module.encoder, _join(prefix, "encoder"),
                                                                   features))
    bias = grouped.buffer(_join(prefix, "action_bias")).unsqueeze(1)
    scale = grouped.buffer(_join(prefix, "action_scale")).unsqueeze(1)
    return bias + scale * torch.tanh(pre)


def _flatten(grouped, module: nn.Flatten, prefix: str, obs):
    """QEnsemble's encoder for vectors (``nn.Flatten()`` on ``obs.float()``)."""
    return obs.float().flatten(2)


_FORWARDS: dict[type, Callable] = {
    nn.Sequential: _sequential,
    NatureCNN: _nature_cnn,
    MLPEncoder: _mlp_encoder,
    ImageMeasurementsEncoder: _image_measurements,
    ActorCritic: _actor_critic,
    DuelingQNetwork: _dueling,
    DeterministicActor: _actor,
    nn.Flatten: _flatten,
}


# ----------------------------------------------------------------------------- the loop's entry


def _parts(obs) -> dict:
    return dict(obs) if isinstance(obs, Mapping) else {"": obs}


class Grouper:
    """The grouped networks of one loop, kept between steps (and their stacked weights with
    them), one set per group of ACs that act together; the architectures of the modules seen."""

    def __init__(self):
        self.groups: dict[tuple, list[GroupedNetworks]] = {}
        self._architectures: dict[int, tuple[nn.Module, tuple | None]] = {}

    def architecture(self, module: nn.Module) -> tuple | None:
        """:func:`architecture`, once per module (the module is kept, so its id stays its own)."""
        found = self._architectures.get(id(module))
        if found is None or found[0] is not module:
            found = self._architectures[id(module)] = (module, architecture(module))
        return found[1]

    def key(self, agent, obs, deterministic: bool) -> tuple | None:
        """What ACs must share to act in one grouped forward pass this step (class, device, the
        acting modules' architecture, the observations' shapes and dtypes), or None: this AC
        acts on its own (``batched_acting`` off, no acting chain now, a module without a
        grouped form)."""
        if not getattr(getattr(agent, "config", None), "batched_acting", False):
            return None
        chain = agent.acting_chain(deterministic)
        if not chain:
            return None
        arch = tuple(self.architecture(m) for m in chain)
        if any(a is None for a in arch):
            return None
        shapes = tuple((key, np.shape(array), str(np.asarray(array).dtype)) for key, array in _parts(obs).items())
        return type(agent), str(agent.device), arch, shapes

    def networks(self, chains: Sequence[Sequence[nn.Module]]) -> list[GroupedNetworks]:
        """The grouped networks of these ACs' acting chains (built at their first step together)."""
        key = tuple(id(m) for chain in chains for m in chain)
        found = self.groups.get(key)
        if found is None or any(g.modules != [c[i] for c in chains] for i, g in enumerate(found)):
            found = self.groups[key] = [GroupedNetworks([c[i] for c in chains]) for i in range(len(chains[0]))]
        return found

    @property
    def copies(self) -> int:
        """Tensors re-copied into stacked weights so far, all groups."""
        return sum(g.copies for found in self.groups.values() for g in found)


def act_all(agents: Mapping[str, Any], requests: Sequence[tuple[str, np.ndarray, Any]], deterministic: bool,
            grouper: Grouper) -> dict[str, np.ndarray]:
    """Every request's actions: ``(agent id, envs, obs)`` -> ``agents[id].act_batch(obs, envs)``,
    with the ACs that :meth:`Grouper.key` puts together (two or more) sharing one grouped
    forward pass; each AC then picks its actions from its slice (``act_from``), all in the order
    of ``requests``, so each AC's generators draw as they did one forward per AC."""
    members: dict[tuple, list[int]] = {}
    for j, (aid, _, obs) in enumerate(requests):
        key = grouper.key(agents[aid], obs, deterministic)
        if key is not None:
            members.setdefault(key, []).append(j)
    outputs: dict[int, Any] = {}
    for rows in members.values():
        if len(rows) < 2:
            continue
        group = [agents[requests[j][0]] for j in rows]
        x = obs_to_tensor(observations.stack([requests[j][2] for j in rows]), group[0].device)
        for grouped in grouper.networks([a.acting_chain(deterministic) for a in group]):
            x = grouped(x)
            if x is None:  # no grouped pass equal to theirs for this shape: each AC acts alone
                break
        else:
            for position, j in enumerate(rows):
                outputs[j] = _slice(x, position)
    actions = {}
    for j, (aid, envs, obs) in enumerate(requests):
        agent = agents[aid]
        if j in outputs:
            actions[aid] = np.asarray(agent.act_from(outputs[j], envs, deterministic))
        else:
            actions[aid] = np.asarray(agent.act_batch(obs, envs, deterministic=deterministic))
    return actions


def _slice(outputs, k: int):
    """The k-th AC's part of a grouped tensor, a tuple of them or a dict of them (nav)."""
    if isinstance(outputs, tuple):
        return tuple(o[k] for o in outputs)
    if isinstance(outputs, Mapping):
        return {key: value[k] for key, value in outputs.items()}
    return outputs[k]
