"""Tests of the worker-process machinery shared by A3C and IMPALA (agents/workers.py).

Rollouts and the env runner are checked against hand-worked cases on fake
envs; the pool is checked for what matters in production: a worker's
exception reaches the parent with its traceback, and no worker survives a
normal end, an exception or an interrupt.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.envs import MultiColourBar
from agents.workers import (
    EnvRunner,
    Rollout,
    RolloutBuilder,
    WorkerError,
    WorkerPool,
    get_context,
    linear_learning_rate,
    live_pids,
    worker_seed,
)

REPO_ROOT = Path(__file__).resolve().parents[2]

# ----------------------------------------------------------------------------- worker targets
# Top-level functions: spawn pickles them by name.


def _report_then_wait(link, payload):
    link.send((link.index, os.getpid(), payload))
    while not link.should_stop():
        time.sleep(0.01)


def _raise_value_error(link):
    raise ValueError("boom from a worker")


def _ignore_stop(link):
    link.send((link.index, os.getpid()))
    while True:  # a stuck worker: never looks at the stop event
        time.sleep(0.05)


def _die_by_signal(link):
    os.kill(os.getpid(), signal.SIGKILL)


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


def test_env_runner_cuts_per_agent_rollouts_as_agents_leave():
    # agent_0 lives 3 steps per episode, agent_1 lives 4: the episode lasts 4 env steps.
    env = MultiColourBar([False, False], size=9, episode_length=3)
    runner = EnvRunner(env, ["agent_0", "agent_1"], seed=0)
    rollouts, episodes, env_steps = runner.collect(
        {aid: (lambda obs: (1, -1.1)) for aid in env.possible_agents}, num_steps=10
    )
    assert env_steps == 10
    # Steps 1-4, 5-8 are full episodes, 9-10 a partial one; agent_0 skips steps 4 and 8.
    assert len(rollouts["agent_0"]) == 8 and len(rollouts["agent_1"]) == 10
    assert len(episodes) == 2
    assert [ep.lengths for ep in episodes] == [{"agent_0": 3, "agent_1": 4}] * 2
    agent_1 = rollouts["agent_1"]
    np.testing.assert_array_equal(np.flatnonzero(agent_1.truncateds), [3, 7])
    np.testing.assert_array_equal(agent_1.final_index, [3, 7, 9])
    first_return = episodes[0].returns["agent_1"]
    assert first_return == pytest.approx(agent_1.rewards[:4].sum())


def test_env_runner_rejects_agents_without_a_model():
    env = MultiColourBar([False, False], size=9)
    with pytest.raises(ValueError, match="agent_1"):
        EnvRunner(env, ["agent_0"], seed=0)


def test_worker_seeds_differ_and_repeat():
    assert worker_seed(0, 0) != worker_seed(0, 1)
    assert worker_seed(3, 1) == worker_seed(3, 1)


def test_linear_learning_rate_decays_to_zero():
    optimizer = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    assert linear_learning_rate(optimizer, 0.4, 0, 100) == pytest.approx(0.4)
    assert linear_learning_rate(optimizer, 0.4, 75, 100) == pytest.approx(0.1)
    assert optimizer.param_groups[0]["lr"] == pytest.approx(0.1)
    assert linear_learning_rate(optimizer, 0.4, 120, 100) == 0.0  # overshoot clamps at 0


def test_get_context_refuses_fork():
    with pytest.raises(ValueError, match="fork"):
        get_context("fork")


# ----------------------------------------------------------------------------- pool

# forkserver: workers fork from a server that imported torch once, so each pool
# starts in ~0.05 s; the spawn path is exercised by the trainers' tests.
FORKSERVER = get_context("forkserver")


def _assert_no_workers_left(pids):
    assert live_pids(pids) == []
    assert multiprocessing.active_children() == []


def test_pool_delivers_messages_and_cleans_up():
    with WorkerPool(_report_then_wait, [("x",), ("y",)], context=FORKSERVER) as pool:
        messages = []
        while len(messages) < 2:
            message = pool.get(timeout=30)
            assert message is not None, "no message from the workers within 30 s"
            messages.append(message)
        pids = pool.pids
        assert sorted(live_pids(pids)) == sorted(pids)
    assert sorted((index, pid, payload) for index, pid, payload in messages) == [
        (0, pids[0], "x"),
        (1, pids[1], "y"),
    ]
    _assert_no_workers_left(pids)


def test_worker_exception_is_raised_in_parent_with_its_traceback():
    with pytest.raises(WorkerError) as info:
        with WorkerPool(_raise_value_error, [()], context=FORKSERVER) as pool:
            pids = pool.pids
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                pool.get(timeout=0.2)
    error = info.value
    assert error.worker_index == 0
    assert "ValueError: boom from a worker" in str(error)
    assert "_raise_value_error" in error.worker_traceback  # the worker's frame, not the parent's
    _assert_no_workers_left(pids)


def test_worker_killed_by_a_signal_is_reported():
    with pytest.raises(WorkerError, match="exited with code"):
        with WorkerPool(_die_by_signal, [()], context=FORKSERVER) as pool:
            pids = pool.pids
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                pool.get(timeout=0.2)
    _assert_no_workers_left(pids)


def test_interrupt_terminates_even_a_stuck_worker():
    with pytest.raises(KeyboardInterrupt):
        with WorkerPool(_ignore_stop, [(), ()], context=FORKSERVER, join_timeout=0.5) as pool:
            pids = pool.pids
            for _ in range(2):
                assert pool.get(timeout=30) is not None
            raise KeyboardInterrupt  # what Ctrl-C does in the parent
    _assert_no_workers_left(pids)


def test_sigterm_to_the_parent_interrupts_and_cleans_up():
    with pytest.raises(KeyboardInterrupt, match="signal 15"):
        with WorkerPool(_report_then_wait, [("x",), ("y",)], context=FORKSERVER) as pool:
            pids = pool.pids
            for _ in range(2):
                assert pool.get(timeout=30) is not None
            os.kill(os.getpid(), signal.SIGTERM)  # what `kill <parent pid>` does
            time.sleep(5)  # the handler interrupts this
    _assert_no_workers_left(pids)


def test_pool_restores_the_sigterm_handler():
    before = signal.getsignal(signal.SIGTERM)
    with WorkerPool(_report_then_wait, [("x",)], context=FORKSERVER) as pool:
        assert signal.getsignal(signal.SIGTERM) is not before
        pool.get(timeout=30)
    assert signal.getsignal(signal.SIGTERM) is before


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
        deadline = time.monotonic() + 90
        while not pid_file.exists() and time.monotonic() < deadline and child.poll() is None:
            time.sleep(0.1)
        assert pid_file.exists(), f"training never reported its workers (exit code {child.poll()})"
        pids = json.loads(pid_file.read_text())
        assert len(pids) == 2 and sorted(live_pids(pids)) == sorted(pids)
        child.send_signal(signum)
        _, stderr = child.communicate(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
            child.communicate()
    assert child.returncode != 0
    if signum == signal.SIGKILL:  # the kernel kills the orphans (PR_SET_PDEATHSIG)
        deadline = time.monotonic() + 10
        while live_pids(pids) and time.monotonic() < deadline:
            time.sleep(0.1)
    else:
        assert "KeyboardInterrupt" in stderr  # the trainer went through its cleanup path
    assert live_pids(pids) == []


_STUCK_POOL_SCRIPT = """
import json, sys, time
sys.path.insert(0, sys.argv[2])
from agents.workers import WorkerPool, get_context
from test_workers import _ignore_stop
with WorkerPool(_ignore_stop, [()], context=get_context("forkserver")) as pool:
    pool.get(timeout=60)
    with open(sys.argv[1], "w") as f:
        json.dump(pool.pids, f)
    time.sleep(600)
"""


def test_a_stuck_worker_dies_with_a_sigkilled_parent(tmp_path):
    # No cleanup code runs on SIGKILL and the worker never checks the stop event:
    # only the kernel's parent-death signal can stop it.
    pid_file = tmp_path / "pids.json"
    python_path = os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))
    log = (tmp_path / "stderr.txt").open("w")  # the orphaned resource tracker warns there
    child = subprocess.Popen(
        [sys.executable, "-c", _STUCK_POOL_SCRIPT, str(pid_file), str(Path(__file__).parent)],
        env={**os.environ, "PYTHONPATH": python_path}, stderr=log,
    )
    try:
        deadline = time.monotonic() + 60
        while not pid_file.exists() and time.monotonic() < deadline and child.poll() is None:
            time.sleep(0.1)
        assert pid_file.exists(), f"the pool never started: {(tmp_path / 'stderr.txt').read_text()}"
        pids = json.loads(pid_file.read_text())
        assert live_pids(pids) == pids
        child.kill()
        child.wait(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        log.close()
    deadline = time.monotonic() + 10
    while live_pids(pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert live_pids(pids) == []


def test_env_runner_scales_rollout_rewards_but_reports_raw_returns():
    env = MultiColourBar([False, False], size=9, episode_length=3)
    runner = EnvRunner(env, ["agent_0", "agent_1"], seed=0, reward_scale=0.1)
    raw = EnvRunner(MultiColourBar([False, False], size=9, episode_length=3), ["agent_0", "agent_1"], seed=0)
    policies = {aid: (lambda obs: (1, -1.1)) for aid in env.possible_agents}
    rollouts, episodes, _ = runner.collect(policies, num_steps=4)
    raw_rollouts, raw_episodes, _ = raw.collect(policies, num_steps=4)
    np.testing.assert_allclose(rollouts["agent_1"].rewards, 0.1 * raw_rollouts["agent_1"].rewards, rtol=1e-6)
    assert np.abs(raw_rollouts["agent_1"].rewards).sum() > 0
    assert episodes[0].returns == raw_episodes[0].returns
