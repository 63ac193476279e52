"""The test protocol (SPEC §6): its plan (:class:`ProtocolPlan`) and rules; its episodes record
every step, and the report (SPEC §7) is written from those records by :mod:`eval.reporting.report`.

Scenario 1 (multi-agent): the trained ACs, one per algorithm, drive together in
each environment among background cars (and pedestrians in env_2/env_3);
discrete and continuous agents share one environment.
Scenario 2 (single-agent): each AC alone, no other vehicles, no pedestrians.

In Scenario 1 the algorithms take turns at the spawn points: in episode ``e`` the
algorithm at position ``i`` of the order drives slot ``ac_{(i + e) mod N}``
(:func:`slot_order`), so no algorithm is tied to one spawn (in env_1 with 6 ACs ``ac_0``
starts 25 m behind ``ac_4`` and ``ac_2`` 25 m behind ``ac_5`` in the same lane; the other
slots have a free lane ahead).
With a multiple of N episodes every algorithm starts from every spawn equally often.
``ProtocolPlan(rotate=False)`` keeps algorithm ``i`` in ``ac_i``.

Collisions do not end an episode in testing (the metrics count steps in
collision). Every step of every AC is recorded (:mod:`eval.testing.records`); metrics,
tables and plots are computed from those records.

The protocol's parts, one module each (this one holds the plan and its rules):

- :mod:`eval.testing.checkpoints`: which checkpoint represents each algorithm (the newest run
  under ``--runs``, the run's chosen AC, the AC trained in a slot, a cross-environment test);
- :mod:`eval.testing.loading`: loading a checkpoint for an AC slot and wrapping it in the
  policy of its observation variant, frame stack and action repeat;
- :mod:`eval.testing.slots`: the table of which checkpoint drives which slot where;
- :mod:`eval.testing.policies`: the policy factories (trained, autopilot, random) the test's
  environments and its worker processes ask for each AC's policy;
- :mod:`eval.testing.jobs`: the jobs (one environment each) and running them, in worker
  processes and resumably;
- :mod:`eval.testing.session`: one test session, :func:`~eval.testing.session.run_test`, that
  `cosim test`, `cosim benchmark`'s report and the studies call.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from agents import registry
from cosim.errors import CosimError
from eval.labels import ENVS

ALGO_ORDER = tuple(registry.ALGORITHMS)  # the catalogue's order (agents/registry.py)
CONTINUOUS = registry.CONTINUOUS
SAMPLED = registry.STOCHASTIC
"""Algorithms whose learned policy is a distribution (the catalogue's ``stochastic``: PPO,
A3C, IMPALA): the test samples it (their training maximised the return of the sampled
policy; its mode is a different policy: two IMPALA modes crawled at 8-14 km/h and reached no goal where their samples drove;
task version 1; in git history at 1b59d82, docs/results/2026-11-23-greedy-vs-sampled). DQN, DDPG and TD3 learn a
deterministic policy and act greedily (no epsilon, no action noise). ``cosim test
--greedy`` takes every policy's mode."""


class ProtocolError(CosimError, ValueError):
    """The test cannot run as asked; the message says what to change."""


@dataclass(frozen=True)
class ProtocolPlan:
    """What a test drives: its environments and scenarios, episodes of ``steps`` steps (None: the
    scenario's horizon) on
    episode seeds ``seed``, ``seed + 1``, ..., Scenario 1 with ``agents`` ACs (rotated over
    the slots unless ``rotate`` is False), and each policy's mode with ``greedy``."""

    envs: tuple[str, ...] = ENVS
    scenarios: tuple[int, ...] = (1, 2)
    episodes: int = 3
    steps: int | None = None
    """Steps per test episode; None (the default): each scenario's own ``horizon`` (its YAML's, 600
    for the bundled environments), the one source of the test's episode length (docs/task.md)."""
    seed: int = 0
    agents: int = 6
    rotate: bool = True
    greedy: bool = False  # True: every policy's mode, also for SAMPLED algorithms


def rules(plan: ProtocolPlan) -> dict[str, str]:
    """How the plan places ACs and picks actions, in words (report provenance, science plan)."""
    return {
        "scenario_1_slots": ("rotated: algorithm i drives ac_{(i + episode) mod N}" if plan.rotate
                             else "fixed: algorithm i drives ac_i"),
        "slot_checkpoints": "a run's AC trained in a slot drives that slot; other slots the "
                            "checkpoint listed (eval.testing.checkpoints.slot_checkpoint)",
        "actions": ("every policy's mode (--greedy)" if plan.greedy else
                    f"{', '.join(SAMPLED)} sample their policy; {', '.join(registry.DETERMINISTIC)} "
                    "greedy (eval.testing.protocol.SAMPLED)"),
    }


def slot_order(algos: Sequence[str], episode: int, rotate: bool = True) -> list[str]:
    """The algorithm of each Scenario 1 slot (``ac_0``, ``ac_1``, ...) in ``episode``:
    algorithm ``i`` drives slot ``(i + episode) mod N`` (module docstring)."""
    algos = list(algos)
    r = episode % len(algos) if rotate and algos else 0
    return algos[len(algos) - r:] + algos[: len(algos) - r]

