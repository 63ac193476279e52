"""One test session: what `cosim test`, `cosim benchmark`'s report and the studies run.

A :class:`TestRequest` says what to test: the plan (eval/testing/protocol.py), the algorithm
of each AC, the policies that drive them (trained checkpoints per environment, or a reference
policy), and what else the session runs: the reference rows, failure replays, cross-play and
sweeps, in how many worker processes. :func:`run_test` runs it and returns a
:class:`TestResult`; the report is written from the result by
:func:`eval.reporting.report.write_paper_report`, the one report writer.

    request = TestRequest(ProtocolPlan(envs=("env_1",)), ("ppo", "dqn"),
                          checkpoints={"env_1": {"ppo": ppo_path, "dqn": dqn_path}})
    result = run_test(request)            # result.records: every step of every AC

With ``out`` each job's records are kept in ``out/episodes`` as it ends: a session
interrupted and run again with the same request and ``out`` runs only the rest
(:func:`eval.testing.jobs.run_protocol`'s ``save``), and the failure replays go to ``out``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from eval.testing.jobs import run_protocol
from eval.testing.policies import PolicyFactory, env_policy_factory, policy_factory
from eval.testing.protocol import ALGO_ORDER, ProtocolError, ProtocolPlan
from eval.testing.slots import slot_table

POLICIES = ("trained", "autopilot", "random")
"""What drives the ACs of a session: trained checkpoints, or one reference policy for all."""

PhaseStart = Callable[[str, "int | None", str], Callable[[str], None] | None]
"""Told as each phase of a session starts (``test``, ``references``, ``replays``,
``cross-play``, ``sweep <kind>``), with its step count and unit; returns the callback told the
name of each step as it ends (or None). `cosim test` passes its progress bars'."""


@dataclass(frozen=True)
class TestRequest:
    """What one test session runs (module docstring)."""

    __test__ = False  # not a pytest test class, despite its name

    plan: ProtocolPlan
    """Environments, scenarios, episodes, steps, episode seeds, slot rotation, greedy actions."""
    algos: tuple[str, ...] = ALGO_ORDER
    """The algorithm of each AC, in order (Scenario 1 takes the first ``plan.agents``); an
    algorithm may be listed more than once (a run's ACs all driven by that run)."""
    checkpoints: Mapping[str, Mapping[str, Path]] | None = None
    """Environment -> algorithm -> checkpoint, for ``policy`` "trained"; each slot is driven by
    the run's AC trained in it where there is one (eval.testing.checkpoints.slot_checkpoint)."""
    policy: str = "trained"
    """One of :data:`POLICIES`: "autopilot" or "random" drive every AC instead of checkpoints."""
    fixed: tuple[str, ...] = ()
    """Algorithms whose checkpoint drives every slot (`cosim test --checkpoint`)."""
    references: tuple[str, ...] = ()
    """Reference policies (eval.testing.validity.POLICIES) run under the plan's Scenario 1 conditions."""
    replays: bool = False
    """Re-run each algorithm's first collision and keep its clips and SUMO state (needs ``out``)."""
    labels: Mapping[str, str] = field(default_factory=dict)
    """Algorithm -> the report's column label, for the replays' titles."""
    cross_play: int = 0
    """ACs per cross-play episode (the ego among partners of one policy); 0: no cross-play."""
    sweeps: Mapping[str, Sequence[float]] = field(default_factory=dict)
    """Perturbation -> levels (eval.testing.robustness.parse_sweeps)."""
    workers: int = 1
    """Processes running the plan's jobs (the records are the same as with one)."""
    encoder: str | None = None
    """The frozen encoder file of the checkpoints trained with ``--encoder`` (`cosim test
    --encoder`); None: the file each such run recorded. Its hash must be the run's."""

    def __post_init__(self):
        if self.policy not in POLICIES:
            raise ProtocolError(f"unknown policy kind {self.policy!r}; valid: {', '.join(POLICIES)}")
        if self.policy != "trained":
            if self.checkpoints or self.fixed:
                raise ProtocolError(f"checkpoints are for policy 'trained', not {self.policy!r}")
            return
        missing = [f"{env}: {algo}" for env in self.plan.envs for algo in dict.fromkeys(self.algos)
                   if algo not in (self.checkpoints or {}).get(env, {})]
        if missing:
            raise ProtocolError(f"no checkpoint given for {', '.join(missing)}; give one per "
                                "environment tested and algorithm (checkpoints[env][algo])")

    @functools.cached_property
    def policies(self) -> PolicyFactory:
        """The policy factory of the ACs, made on first use: each checkpoint given is loaded
        then, so a file that cannot drive its slot fails before any episode runs.

        Raises:
            ProtocolError: a checkpoint holds another algorithm, action space or camera size, or its
                run's frozen encoder is missing or not the file given (eval.testing.loading.frame_encoder).
            agents.CheckpointError: a checkpoint is missing or corrupt.
        """
        if self.policy != "trained":
            return policy_factory(self.policy, None, greedy=self.plan.greedy)
        return env_policy_factory(self.checkpoints, fixed=self.fixed, greedy=self.plan.greedy, encoder=self.encoder)

    @property
    def slots(self) -> pd.DataFrame | None:
        """Which checkpoint drives which slot in which environment (eval.testing.slots.slot_table);
        None for a reference policy."""
        if self.policy != "trained":
            return None
        return slot_table(self.checkpoints, self.plan, self.algos, fixed=self.fixed)


@dataclass(frozen=True)
class TestResult:
    """What a session ran: the records the report is written from, and the extras asked for."""

    __test__ = False

    request: TestRequest
    records: pd.DataFrame
    """Every step of every AC (eval.testing.records), in the plan's job order."""
    references: pd.DataFrame | None = None
    """The reference rows (:func:`reference_rows`); None when none were asked for."""
    replays: list[dict] = field(default_factory=list)
    """One entry per failure replay written (eval.testing.replay.capture)."""
    cross_play: pd.DataFrame | None = None
    """Cross-play records (eval.testing.robustness.run_cross_play); None without cross-play."""
    sweeps: dict[str, pd.DataFrame] = field(default_factory=dict)
    """Perturbation -> its records at every level (eval.testing.robustness.run_sweep)."""


def protocol_steps(plan: ProtocolPlan, algos: Sequence[str]) -> int:
    """Steps of a session's ``test`` phase: one per environment's Scenario 1, one per AC alone."""
    return len(plan.envs) * ((1 in plan.scenarios) + (2 in plan.scenarios) * len(algos))


def run_test(request: TestRequest, out: Path | None = None, phases: PhaseStart | None = None) -> TestResult:
    """Run one test session: the plan's episodes, then the references, the failure replays,
    cross-play and sweeps the request asks for, in that order.

    ``out``: the session's folder; each job's records are kept in ``out/episodes`` as it ends
    (a session run again with the same request and ``out`` goes on from them) and the replays
    are written there. ``phases`` is told as each phase starts (:data:`PhaseStart`).

    Raises:
        ProtocolError: replays without ``out``; ``out/episodes`` holds another plan's episodes
            or cannot be written; a checkpoint cannot drive its slot.
    """
    if request.replays and out is None:
        raise ProtocolError("failure replays are written into the session's folder; give run_test an out")
    plan, algos = request.plan, list(request.algos)
    start = phases or (lambda name, total, unit: None)
    records = run_protocol(plan, request.policies, algos, progress=start("test", protocol_steps(plan, algos), "run"),
                           workers=request.workers, save=None if out is None else Path(out) / "episodes")
    refs = (reference_rows(plan, request.references, progress=start("references", len(plan.envs), "env"))
            if request.references else None)
    replays = []
    if request.replays:
        from eval.testing import replay

        replays = replay.capture(plan, request.policies, algos, records, Path(out), dict(request.labels),
                                 progress=start("replays", replay.reruns(records), "run"))
    cross, swept = None, {}
    if request.cross_play or request.sweeps:
        from eval.testing import robustness

        if request.cross_play:
            cross = robustness.run_cross_play(plan, request.policies, algos, group=request.cross_play, progress=start(
                "cross-play", len(plan.envs) * len(algos) * (len(algos) + 1), "run"))
        swept = {kind: robustness.run_sweep(plan, request.policies, algos, kind, levels,
                                            progress=start(f"sweep {kind}", len(levels) * len(plan.envs), "run"))
                 for kind, levels in request.sweeps.items()}
    return TestResult(request, records, refs, replays, cross, swept)


def reference_rows(plan: ProtocolPlan, policies: Sequence[str],
                   progress: Callable[[str], None] | None = None) -> pd.DataFrame:
    """The reference policies of eval.testing.validity (the continuous and discrete autopilots, the
    safe non-turner, random and the degenerate policies) under the plan's Scenario 1
    conditions: same environments, AC count, steps and episodes."""
    from eval.testing import validity

    frames = []
    for env_name in plan.envs:
        rows = validity.check_scenario(env_name, plan.agents, plan.episodes, plan.steps,
                                       policies=tuple(policies))
        frames.append(validity.summarize(rows).reset_index().assign(env=env_name))
        if progress:
            progress(f"{env_name} references")
    return pd.concat(frames, ignore_index=True)
