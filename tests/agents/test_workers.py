"""Tests of what the vector env and the asynchronous trainers share (agents/workers.py,
agents/async_env.py), and of signals sent to an A3C/IMPALA training process.

Rollouts are checked against hand-worked cases; batched acting, recording and
episode tracking on a scripted vector env whose observations encode env, agent
and step; concurrent stepping of disjoint envs from threads (A3C's learner
threads) against the env each thread owns; and no env worker survives a signal
to the trainer.
"""

from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.async_env import Unrolls, vector_env
from agents.envs import ScriptedParallelEnv
from agents.impala import IMPALA, IMPALAConfig
from agents.loop import run_loop
from agents.vector import InProcessVectorEnv, VectorEnv
from agents.workers import (
    Rollout,
    RolloutBuilder,
    get_context,
    live_pids,
    worker_seed,
)

REPO_ROOT = Path(__file__).resolve().parents[2]


# ----------------------------------------------------------------------------- rollouts


def _obs(value: float) -> np.ndarray:
    return np.full(2, value, dtype=np.float32)


def test_rollout_builder_keeps_next_obs_only_at_boundaries():
    builder = RolloutBuilder("a")
    builder.add(_obs(0), 1, 1.0, _obs(1), False, False, -0.5)
    builder.add(_obs(1), 0, 2.0, _obs(2), False, True, -0.6)  # truncated: final obs is _obs(2)
    builder.add(_obs(10), 1, 3.0, _obs(11), False, False, -0.7)  # after a reset
    rollout = builder.build()

    assert len(rollout) == 3 and len(builder) == 0
    np.testing.assert_array_equal(rollout.final_index, [1, 2])
    np.testing.assert_array_equal(rollout.final_obs, [_obs(2), _obs(11)])
    np.testing.assert_array_equal(rollout.boundaries, [False, True, True])
    np.testing.assert_array_equal(rollout.dones, [False, True, False])
    np.testing.assert_allclose(rollout.log_probs, [-0.5, -0.6, -0.7])

    values = np.array([10.0, 20.0, 30.0], dtype=np.float32)
    next_values = rollout.next_values(values, lambda obs: obs[:, 0] * 100)
    # step 0 -> V(obs[1]) = 20; steps 1 and 2 -> value_fn of their final obs.
    np.testing.assert_allclose(next_values, [20.0, 200.0, 1100.0])


def test_rollout_builder_marks_a_gap_in_the_stream_as_a_boundary():
    builder = RolloutBuilder("a")
    builder.add(_obs(0), 0, 0.0, _obs(1), False, False)
    builder.add(_obs(5), 0, 0.0, _obs(6), False, False)  # obs is not the previous next_obs
    rollout = builder.build()
    np.testing.assert_array_equal(rollout.final_index, [0, 1])
    np.testing.assert_array_equal(rollout.final_obs[0], _obs(1))


def test_rollout_concat_shifts_boundaries():
    parts = []
    for start in (0, 100):
        builder = RolloutBuilder("a")
        for t in range(3):
            builder.add(_obs(start + t), 0, 1.0, _obs(start + t + 1), False, False)
        parts.append(builder.build())
    batch = Rollout.concat(parts)
    assert len(batch) == 6
    np.testing.assert_array_equal(batch.final_index, [2, 5])
    np.testing.assert_array_equal(batch.final_obs, [_obs(3), _obs(103)])


def test_rollout_builder_refuses_an_empty_build():
    with pytest.raises(ValueError, match="no transitions"):
        RolloutBuilder("a").build()


def test_worker_seeds_differ_and_repeat():
    assert worker_seed(0, 0) != worker_seed(0, 1)
    assert worker_seed(3, 1) == worker_seed(3, 1)


def test_get_context_refuses_fork():
    with pytest.raises(ValueError, match="fork"):
        get_context("fork")


# ----------------------------------------------------------------------------- async_env on a scripted vector env

LENGTHS = (3, 5, 4)


def _scripted(n: int, **kwargs):
    return [functools.partial(ScriptedParallelEnv, i, **{"lengths": LENGTHS, **kwargs}) for i in range(n)]


def test_loop_hooks_cut_unrolls_per_env_and_agent_across_auto_resets():
    # IMPALA's hooks on the one loop (learning off: unrolls longer than the run): every
    # transition reaches its (env, agent) unroll with the acting policy's log-probability and
    # the TRUE final observation at an episode end; the loop reports each env's episodes.
    seed, n, scale = 3, 2, 0.5
    config = IMPALAConfig(unroll_length=1000, batch_size=1, reward_scale=scale)
    reports = []
    with InProcessVectorEnv(_scripted(n)) as venv:
        space, actions = venv.observation_space("agent_0"), venv.action_space("agent_0")
        learners = {a: IMPALA.from_spaces(space, actions, config, seed=k) for k, a in enumerate(venv.possible_agents)}
        run_loop(learners, venv, 30 * n, callback=reports.append, seed=seed)
    assert all(not r.metrics for r in reports) and reports[-1].env_steps == 30 * n
    rollouts = [(aid, env, rollout, version) for aid, learner in learners.items()
                for _, env, rollout, version in learner._unrolls.take_all()]
    episodes = [episode for r in reports for episode in r.episodes]
    for aid, _env, rollout, _version in rollouts:
        with torch.no_grad():
            logits, _ = learners[aid].model(torch.as_tensor(rollout.obs))
        expected = torch.log_softmax(logits, -1).numpy()[np.arange(len(rollout)), rollout.actions]
        np.testing.assert_allclose(rollout.log_probs, expected, rtol=1e-5)  # the acting policy's
    assert sorted((a, e) for a, e, _, _ in rollouts) == [(a, e) for a in venv.possible_agents for e in range(n)]
    for aid, env, rollout, _ in rollouts:
        k = int(aid[-1])
        final = dict(zip(rollout.final_index.tolist(), rollout.final_obs, strict=True))
        episode = 0
        for t in range(len(rollout)):
            obs = rollout.obs[t]
            nxt = final[t] if t in final else rollout.obs[t + 1]
            assert (obs[0], obs[1], obs[3]) == (env, k, seed + env + episode * n)
            assert (nxt[0], nxt[1], nxt[2], nxt[3], nxt[4]) == (env, k, obs[2] + 1, obs[3], rollout.actions[t])
            assert rollout.rewards[t] == pytest.approx(scale * (nxt[2] + 100 * env + 10 * k))
            ends = nxt[2] == LENGTHS[k] + obs[3] % 3
            assert bool(rollout.dones[t]) == ends and bool(rollout.terminateds[t]) == (ends and k % 2 == 0)
            if ends:
                assert t in final and nxt[2] > 0  # the TRUE final observation, not the reset one
                episode += 1
    for report in episodes:  # raw returns, the env's own summary, per env
        i = report.worker
        assert set(report.lengths) == set(learners)
        for aid, length in report.lengths.items():
            k = int(aid[-1])
            assert report.extras[aid] == {"t": length}
            assert report.returns[aid] == pytest.approx(sum(t + 100 * i + 10 * k for t in range(1, length + 1)))
    assert {r.worker for r in episodes} == {0, 1}


def test_unrolls_cut_at_the_length_and_remember_the_first_version():
    unrolls = Unrolls()
    obs = np.zeros(5, np.float32)
    for t in range(5):
        unrolls.add("a", 0, obs + t, 1, 1.0, obs + t + 1, False, False, -0.1, version=t)
    (ready,) = unrolls.take_ready(3)
    assert ready[:2] == ("a", 0) and len(ready[2]) == 5 and ready[3] == 0
    unrolls.add("a", 0, obs, 1, 1.0, obs, False, False, -0.1, version=9)
    assert unrolls.take_ready(3) == [] and unrolls.take_all()[0][3] == 9


def test_vector_env_wraps_a_gymnasium_factory_and_checks_counts():
    import gymnasium

    with vector_env(functools.partial(gymnasium.make, "CartPole-v1"), 1) as venv:
        assert isinstance(venv, InProcessVectorEnv) and venv.possible_agents == ["agent_0"]
    with pytest.raises(ValueError, match="num_envs=3 but 2 env factories"):
        vector_env(_scripted(2), 3)


@pytest.mark.parametrize("kind", ["in-process", "processes"])
def test_threads_step_disjoint_envs_concurrently(kind):
    # A3C's learner threads: thread k steps only env k, each with its own step_async/step_wait.
    n, steps = 3, 40
    cls = InProcessVectorEnv if kind == "in-process" else functools.partial(VectorEnv, start_method="forkserver")
    errors = []
    with cls(_scripted(n, num_agents=1, lengths=(1000,))) as venv:
        state = venv.reset(seed=0)

        def own(k: int) -> None:
            try:
                for t in range(1, steps + 1):
                    venv.step_async({"agent_0": np.full(n, k % 3)}, [k])
                    out = venv.step_wait([k])
                    assert out.stepped.tolist() == [i == k for i in range(n)]
                    assert out.next_obs["agent_0"][k].tolist() == [k, 0, t, k, k % 3]
                    assert out.rewards["agent_0"][k] == t + 100 * k
            except BaseException as exc:  # noqa: BLE001 - reported below
                errors.append(exc)

        threads = [threading.Thread(target=own, args=(k,)) for k in range(n)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=60)
        assert state.obs["agent_0"][:, 0].tolist() == list(range(n))
    assert errors == []


def test_in_process_step_wait_without_step_async_is_refused():
    with InProcessVectorEnv(_scripted(2)) as venv:
        venv.reset(seed=0)
        venv.step_async({a: np.ones(2, np.int64) for a in venv.possible_agents}, [0])
        with pytest.raises(RuntimeError, match=r"step_wait\(\[1\]\) without a step_async"):
            venv.step_wait([1])
        assert venv.step_wait([0]).stepped.tolist() == [True, False]


# ----------------------------------------------------------------------------- signals to a trainer

_TRAIN_SCRIPT = """
import functools, json, sys
import gymnasium, numpy as np
from agents.{module} import {train}
def write_pids(progress):
    with open(sys.argv[1] + ".tmp", "w") as f:
        json.dump(progress.worker_pids, f)
    __import__("os").replace(sys.argv[1] + ".tmp", sys.argv[1])
spaces = (gymnasium.spaces.Box(-np.inf, np.inf, (4,), np.float32), gymnasium.spaces.Discrete(2))
{train}(functools.partial(gymnasium.make, "CartPole-v1"), *spaces, total_steps=10**9,
        callback=write_pids, start_method="{start_method}")
"""


# The trainer's cleanup is bounded by its own timeouts (agents/loop.py _run_actor_threads: each
# learner thread joined for 10 s, the env workers closed in ~7 s, the threads joined again for
# 5 s): ~40 s at worst with two envs. Three times that, so load never fails the test and a hang
# still does.
TRAINER_EXIT_S = 120


@pytest.mark.parametrize(
    "module, train, start_method, signum",
    [
        ("a3c", "train_a3c", "forkserver", signal.SIGINT),  # Ctrl-C
        # The spawn start takes ~10-20 s on 2 busy cores: these are not in the default run.
        pytest.param("impala", "train_impala", "spawn", signal.SIGTERM, marks=pytest.mark.slow),  # kill <pid>
        pytest.param("a3c", "train_a3c", "spawn", signal.SIGKILL, marks=pytest.mark.slow),  # no cleanup code runs
    ],
)
def test_signal_to_the_training_process_leaves_no_worker(tmp_path, module, train, start_method, signum):
    pid_file = tmp_path / "pids.json"
    python_path = os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))
    script = _TRAIN_SCRIPT.format(module=module, train=train, start_method=start_method)
    child = subprocess.Popen(
        [sys.executable, "-c", script, str(pid_file)],
        env={**os.environ, "PYTHONPATH": python_path}, stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + 180  # process start and forkserver, on a loaded machine
        while not pid_file.exists() and time.monotonic() < deadline and child.poll() is None:
            time.sleep(0.1)
        assert pid_file.exists(), f"training never reported its workers (exit code {child.poll()})"
        pids = json.loads(pid_file.read_text())
        assert len(pids) == 2 and sorted(live_pids(pids)) == sorted(pids)
        child.send_signal(signum)
        _, stderr = child.communicate(timeout=TRAINER_EXIT_S)
    finally:
        if child.poll() is None:
            child.kill()
            child.communicate()
    assert child.returncode != 0
    if signum == signal.SIGKILL:  # the kernel kills the orphans (PR_SET_PDEATHSIG)
        deadline = time.monotonic() + 30
        while live_pids(pids) and time.monotonic() < deadline:
            time.sleep(0.1)
    else:
        assert "KeyboardInterrupt" in stderr  # the trainer went through its cleanup path
    assert live_pids(pids) == []
