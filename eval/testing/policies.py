"""How each AC of a test gets its policy: the policy factories (trained checkpoints, the
autopilot, random) that the test's environments call per AC slot, each an object a worker
process can receive (eval/testing/jobs.py)."""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
from pathlib import Path

from eval.testing.checkpoints import slot_checkpoint
from eval.testing.loading import drive, load_for_slot
from eval.testing.protocol import SAMPLED, ProtocolError
from eval.testing.rollout import AutopilotPolicy, RandomPolicy

PolicyFactory = Callable[[object, str, str], object]  # (env, agent id, algorithm) -> policy


def slot_index(agent: str) -> int:
    """k of slot ``ac_k``: the seed of that slot's draws."""
    return int(agent.rsplit("_", 1)[1])


class TrainedPolicies:
    """:func:`policy_factory` ("trained"), as an object a test worker process can receive:
    pickled without the loaded networks, it loads each checkpoint again where it runs."""

    def __init__(self, checkpoints: dict[str, Path] | None = None, fixed: Collection[str] = (),
                 greedy: bool = False, loaded: dict | None = None, encoder: Path | str | None = None):
        self.checkpoints = dict(checkpoints or {})
        self.fixed, self.greedy = tuple(fixed), greedy
        self.encoder = encoder  # `cosim test --encoder`: the file of the runs trained with --encoder
        self.loaded = {} if loaded is None else loaded
        for a, p in self.checkpoints.items():  # the given ones load now: a bad file fails before any episode runs
            if p not in self.loaded:
                self.loaded[p] = load_for_slot(p, a, encoder=encoder)

    def __call__(self, env, agent: str, algo: str):
        path = (self.checkpoints[algo] if algo in self.fixed
                else slot_checkpoint(self.checkpoints[algo], agent))
        if path not in self.loaded:
            self.loaded[path] = load_for_slot(path, algo, encoder=self.encoder)
        seed = slot_index(agent) if algo in SAMPLED and not self.greedy else None
        return drive(self.loaded[path], seed, env, agent)  # one frame history (and draw stream) per AC

    def __getstate__(self) -> dict:
        return {**self.__dict__, "loaded": {}}


class EnvPolicies:
    """:func:`env_policy_factory`'s factory: each environment's own :class:`TrainedPolicies`."""

    def __init__(self, by_name: dict[str, TrainedPolicies]):
        self.by_name = by_name

    def __call__(self, env, agent: str, algo: str):
        return self.by_name[env.scenario.name](env, agent, algo)


class ReferencePolicies:
    """``--policy autopilot`` or ``random`` for every AC (random seeded by the AC's slot)."""

    def __init__(self, kind: str):
        self.kind = kind

    def __call__(self, env, agent: str, algo: str):
        if self.kind == "autopilot":
            return AutopilotPolicy(env, agent)
        return RandomPolicy(env.action_space(agent), seed=slot_index(agent))


def env_policy_factory(per_env: Mapping[str, Mapping[str, Path]], fixed: Collection[str] = (),
                       greedy: bool = False, encoder: Path | str | None = None) -> PolicyFactory:
    """:func:`policy_factory` ("trained") with each environment's own checkpoints
    (``per_env``: environment name or scenario file -> algorithm -> checkpoint); a checkpoint
    several environments share is loaded once."""
    from cosim.scenario import load_scenario

    loaded: dict[Path, object] = {}
    return EnvPolicies({load_scenario(env).name: TrainedPolicies(dict(ckpts), fixed, greedy, loaded, encoder)
                        for env, ckpts in per_env.items()})


def policy_factory(kind: str, checkpoints: dict[str, Path] | None = None,
                   fixed: Collection[str] = (), greedy: bool = False,
                   loaded: dict | None = None, encoder: Path | str | None = None) -> PolicyFactory:
    """How each AC gets its policy: trained checkpoints, the autopilot, or random.

    Trained: slot ``ac_k`` of algorithm ``a`` is driven by :func:`~eval.testing.checkpoints.slot_checkpoint`
    (the run's own ``ac_k`` where it trained one), except for the algorithms in
    ``fixed`` (given with ``--checkpoint``), whose checkpoint drives every slot. The
    :data:`~eval.testing.protocol.SAMPLED` algorithms draw their actions from their policy (seeded per slot
    and episode) unless ``greedy``; the others act greedily. ``loaded``: a cache of loaded
    checkpoints (path -> agent) to share with other factories; ``encoder``: the frozen encoder
    file of the checkpoints trained with ``--encoder`` (default: the one each run recorded; its
    hash is checked, eval.testing.loading.frame_encoder). Every factory returned can be
    pickled, so :func:`~eval.testing.jobs.run_protocol` can hand it to worker processes."""
    if kind == "trained":
        return TrainedPolicies(checkpoints, fixed, greedy, loaded, encoder)
    if kind in ("autopilot", "random"):
        return ReferencePolicies(kind)
    raise ProtocolError(f"unknown policy kind {kind!r}; valid: trained, autopilot, random")

