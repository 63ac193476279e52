"""Running the test protocol's episodes (eval/testing/protocol.py): the plan cut into jobs,
one environment each (:func:`protocol_jobs`), run here or in worker processes that end with
this one, each job's records kept as it ends so an interrupted test goes on from them
(:func:`run_protocol`)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from eval.testing.conditions import TestConditions, action_kinds
from eval.testing.policies import PolicyFactory
from eval.testing.protocol import ALGO_ORDER, ProtocolError, ProtocolPlan, slot_order
from eval.testing.rollout import run_episodes, use_cameras


@dataclass(frozen=True)
class ProtocolJob:
    """One environment of the test: a Scenario 1 slot order with the episodes that use it,
    or one algorithm's AC alone (Scenario 2) for every episode."""

    env: str
    scenario: int
    order: tuple[str, ...]  # the algorithm of ac_0, ac_1, ...
    episodes: tuple[int, ...]


def protocol_jobs(plan: ProtocolPlan, algos: Sequence[str]) -> list[ProtocolJob]:
    """The plan's environments to run, in the order their records are returned."""
    jobs = []
    for env_name in plan.envs:
        if 1 in plan.scenarios:
            # one environment per slot order (the action types follow the algorithms)
            by_order: dict[tuple[str, ...], list[int]] = {}
            for e in range(plan.episodes):
                by_order.setdefault(tuple(slot_order(algos, e, plan.rotate)), []).append(e)
            jobs += [ProtocolJob(env_name, 1, order, tuple(eps)) for order, eps in by_order.items()]
        if 2 in plan.scenarios:
            jobs += [ProtocolJob(env_name, 2, (algo,), tuple(range(plan.episodes))) for algo in algos]
    return jobs


def run_job(plan: ProtocolPlan, make_policy: PolicyFactory, job: ProtocolJob) -> pd.DataFrame:
    """Every step of one :class:`ProtocolJob`'s episodes (episode seeds ``plan.seed + e``)."""
    env = TestConditions.of(job.scenario, plan.steps).env(job.env, action_kinds(list(job.order)))
    try:
        agent_algo = dict(zip(env.possible_agents, job.order, strict=True))
        policies = {a: make_policy(env, a, agent_algo[a]) for a in env.possible_agents}
        use_cameras(env, policies)  # off when no AC reads an image (state-track / reference ACs only)
        rec = run_episodes(env, policies, [plan.seed + e for e in job.episodes], algorithms=agent_algo)
    finally:
        env.close()
    rec["episode"] = rec["episode"].map(dict(enumerate(job.episodes)))
    return rec.assign(env=job.env, scenario=job.scenario)


_WORKER_POLICIES: list = []  # a test worker process's policy factory (set by _start_worker)


def _start_worker(make_policy: PolicyFactory, owner: int | None = None) -> None:
    import torch

    if owner is not None:  # the test's process dies (kill -9, SIGTERM): its workers go too
        from agents.workers import die_with_owner

        die_with_owner(owner)
    torch.set_num_threads(1)  # the workers share the machine's cores
    _WORKER_POLICIES[:] = [make_policy]


def _worker_job(plan: ProtocolPlan, job: ProtocolJob) -> pd.DataFrame:
    return run_job(plan, _WORKER_POLICIES[0], job)


def _job_file(save: Path, k: int) -> Path:
    return save / f"job-{k:03d}.parquet"


def _kept_jobs(save: Path, plan: ProtocolPlan, jobs: list[ProtocolJob]) -> dict[int, pd.DataFrame]:
    """``save``'s records of the jobs an earlier, interrupted run of the same plan finished
    (job index -> records); ``save`` is created and its plan.json written on a first run.

    Raises:
        ProtocolError: ``save`` holds the episodes of another plan, or cannot be written.
    """
    import dataclasses
    import json

    from eval.testing.files import atomic_write, write_message

    def error(p: Path, exc: OSError) -> ProtocolError:
        return ProtocolError(write_message(p, exc, "the episodes already kept are not run again"))

    want = json.loads(json.dumps({"plan": dataclasses.asdict(plan), "jobs": [dataclasses.asdict(j) for j in jobs]}))
    path = save / "plan.json"
    try:
        save.mkdir(parents=True, exist_ok=True)
        if not path.exists():
            atomic_write(path, json.dumps(want, indent=1), error)
            return {}
        saved = json.loads(path.read_text())
    except ProtocolError:
        raise
    except (OSError, ValueError) as exc:
        raise ProtocolError(f"{path}: {exc}; delete {save} to run the test afresh") from None
    if saved != want:
        raise ProtocolError(f"{save} holds the episodes of another test plan ({path}); give the options "
                            "of the test that started it, or another --out")
    kept = {}
    for k in range(len(jobs)):
        if _job_file(save, k).is_file():
            try:
                kept[k] = pd.read_parquet(_job_file(save, k))
            except Exception as exc:  # a file cut by a kill is renamed into place whole, so a bug or a disk fault
                raise ProtocolError(f"{_job_file(save, k)} is unreadable ({type(exc).__name__}); delete it "
                                    "to run its episodes again") from None
    return kept


def _keep_job(save: Path | None, k: int, records: pd.DataFrame) -> None:
    """Write job ``k``'s records under ``save`` (a temporary name, renamed: whole or absent)."""
    if save is None:
        return
    path = _job_file(save, k)
    tmp = path.with_name(path.name + ".tmp")
    try:
        records.to_parquet(tmp, index=False)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        from eval.testing.files import write_message

        raise ProtocolError(write_message(path, exc, "the episodes already kept are not run again")) from exc


def run_protocol(plan: ProtocolPlan, make_policy: PolicyFactory, algos: Sequence[str] = ALGO_ORDER,
                 progress: Callable[[str], None] | None = None, workers: int = 1,
                 save: Path | None = None) -> pd.DataFrame:
    """Run Scenario 1 and/or 2 in every environment of the plan; return all records.

    ``workers`` > 1 runs the plan's :func:`protocol_jobs` in that many processes (each with one
    torch thread, each ending with this process, even on kill -9); the records are the same, in
    the same order, as with one. ``progress`` is told "<env> scenario 1" when an environment's
    Scenario 1 is done and "<env> scenario 2 <algo>" for each AC alone.

    ``save``: a folder where each job's records are written as it ends (``job-<k>.parquet``,
    beside the plan in plan.json); a run interrupted (Ctrl-C, kill -9, a full disk) and started
    again with the same plan and folder runs only the jobs not kept there, and returns the same
    records as one run without interruption.

    Raises:
        ProtocolError: ``save`` holds another plan's episodes, or cannot be written.
    """
    algos = list(algos)[: plan.agents] if 1 in plan.scenarios else list(algos)
    jobs = protocol_jobs(plan, algos)
    left = {env: sum(j.env == env and j.scenario == 1 for j in jobs) for env in plan.envs}

    def done(job: ProtocolJob) -> None:
        if job.scenario == 1:
            left[job.env] -= 1
        if progress and (job.scenario == 2 or not left[job.env]):
            progress(f"{job.env} scenario {job.scenario}" + (f" {job.order[0]}" if job.scenario == 2 else ""))

    save = None if save is None else Path(save)
    results: list[pd.DataFrame | None] = [None] * len(jobs)
    for k, records in (_kept_jobs(save, plan, jobs) if save is not None else {}).items():
        results[k] = records
        done(jobs[k])
    todo = [k for k in range(len(jobs)) if results[k] is None]
    workers = max(1, min(int(workers), len(todo)))
    if workers == 1:
        for k in todo:
            results[k] = run_job(plan, make_policy, jobs[k])
            _keep_job(save, k, results[k])
            done(jobs[k])
        return pd.concat(results, ignore_index=True) if results else pd.DataFrame()
    import multiprocessing
    import pickle
    from concurrent.futures import ProcessPoolExecutor, as_completed

    try:
        pickle.dumps(make_policy)
    except (pickle.PicklingError, AttributeError, TypeError) as exc:
        raise ProtocolError(f"workers={workers}: this policy factory cannot go to another process "
                            f"({exc}); use policy_factory(...) or workers=1") from exc
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_start_worker, initargs=(make_policy, os.getpid()))
    try:
        running = {pool.submit(_worker_job, plan, jobs[k]): k for k in todo}
        for future in as_completed(running):
            k = running[future]
            results[k] = future.result()
            _keep_job(save, k, results[k])
            done(jobs[k])
    except BaseException:  # Ctrl-C, SIGTERM, a failed job: the workers stop now, not after their jobs
        _stop_pool(pool)
        raise
    pool.shutdown()
    return pd.concat(results, ignore_index=True)


def _stop_pool(pool) -> None:
    """End a ProcessPoolExecutor's workers at once (their jobs cancelled) and wait for them."""
    processes = list(getattr(pool, "_processes", {}).values())  # the executor keeps no other handle
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes:
        proc.kill()
    for proc in processes:
        proc.join(timeout=10)

