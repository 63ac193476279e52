"""Tests of IMPALA (agents/impala.py): config, V-trace loss, in-process and actor-learner training.

The learning benchmark (CartPole >= 475) lives in bench/agents_async_reference.py;
these tests run in seconds. Signals sent to a training process are tested in
tests/agents/test_workers.py.
"""

from __future__ import annotations

import functools
import multiprocessing

import gymnasium
import numpy as np
import pytest
import torch

import agents
from agents.a3c import A3CConfig, a3c_loss
from agents.envs import MultiColourBar, SingleAgentParallel
from agents.impala import IMPALA, IMPALAConfig, impala_loss, train_impala
from agents.loop import run_loop
from agents.workers import RolloutBuilder, WorkerError, live_pids

from .conftest import CARTPOLE, CARTPOLE_SPACES, Explodes, model_weights


@torch.no_grad()
def _log_probs(agent, obs: np.ndarray) -> np.ndarray:
    logits, _ = agent.model(torch.as_tensor(obs))
    return torch.log_softmax(logits, -1).numpy()


def _on_policy_rollout(agent, rng, steps: int = 6):
    """A CartPole-shaped rollout whose behaviour log-probs are the agent's own."""
    obs = rng.normal(size=(steps + 1, 4)).astype(np.float32)
    log_probs = _log_probs(agent, obs)
    builder = RolloutBuilder("a")
    for t in range(steps):
        action = t % 2
        builder.add(obs[t], action, 1.0, obs[t + 1], t == 3, False, log_probs[t, action])
    return builder.build()


# ----------------------------------------------------------------------------- config and loss


def test_paper_preset_matches_table_3():
    config = IMPALAConfig.preset("paper")
    assert (config.learning_rate, config.vf_coef, config.ent_coef) == (1e-4, 0.5, 0.01)
    assert not config.anneal_lr
    assert (config.rho_bar, config.c_bar, config.max_grad_norm) == (1.0, 1.0, 30.0)


def test_config_rejects_bad_values_with_the_field_name():
    with pytest.raises(ValueError, match="rho_bar"):
        IMPALAConfig(rho_bar=0.0)
    with pytest.raises(ValueError, match="unroll_length"):
        IMPALAConfig.preset("paper", unroll_length=0)


def test_on_policy_vtrace_targets_equal_the_a3c_n_step_returns():
    # With mu == pi and rho/c bars of 1, V-trace targets are the lambda=1 returns.
    agent = IMPALA.from_spaces(*CARTPOLE_SPACES, seed=2)
    rollout = _on_policy_rollout(agent, np.random.default_rng(0))
    _, impala_metrics = impala_loss(agent.model, rollout, agent.config)
    _, a3c_metrics = a3c_loss(agent.model, rollout, A3CConfig(gamma=agent.config.gamma, gae_lambda=1.0))
    assert impala_metrics["charts/mean_rho"] == pytest.approx(1.0, abs=1e-5)
    assert impala_metrics["losses/value_loss"] == pytest.approx(a3c_metrics["losses/value_loss"], rel=1e-5)
    assert impala_metrics["losses/policy_loss"] == pytest.approx(a3c_metrics["losses/policy_loss"], rel=1e-4)


def test_policy_gradient_is_weighted_by_the_importance_ratio():
    agent = IMPALA.from_spaces(*CARTPOLE_SPACES, seed=0)
    obs = np.array([0.1, 0.2, -0.1, 0.0], dtype=np.float32)
    pi = float(np.exp(_log_probs(agent, obs[None])[0, 1]))

    def pg_loss(behaviour_log_prob: float) -> float:
        builder = RolloutBuilder("a")
        builder.add(obs, 1, 5.0, obs, True, False, behaviour_log_prob)
        return impala_loss(agent.model, builder.build(), agent.config)[1]["losses/policy_loss"]

    # mu(a) = 1 gives rho = pi(a) < 1: the on-policy gradient scaled by pi(a).
    assert pg_loss(0.0) == pytest.approx(pi * pg_loss(np.log(pi)), rel=1e-4)


# ----------------------------------------------------------------------------- in-process


def test_in_process_learner_trains_through_the_common_loop():
    config = IMPALAConfig(unroll_length=10, batch_size=2)
    agent = IMPALA.from_spaces(*CARTPOLE_SPACES, config, seed=1)
    before = model_weights(agent)
    stats = run_loop({"agent_0": agent}, SingleAgentParallel(CARTPOLE()), total_steps=400, seed=1)
    assert stats.updates == 400 // (10 * 2)
    assert all(np.isfinite(v) for v in stats.last_metrics["agent_0"].values())
    assert not torch.equal(before, model_weights(agent))


def test_checkpoint_round_trip_gives_identical_actions(tmp_path):
    agent = IMPALA.from_spaces(*CARTPOLE_SPACES, IMPALAConfig(unroll_length=10, batch_size=2), seed=3)
    run_loop({"agent_0": agent}, SingleAgentParallel(CARTPOLE()), total_steps=100)
    agent.save(tmp_path / "impala.ckpt")
    loaded = agents.load(tmp_path / "impala.ckpt")
    assert isinstance(loaded, IMPALA) and loaded.config == agent.config
    observations = np.random.default_rng(0).normal(size=(50, 4)).astype(np.float32)
    assert [agent.act(o, deterministic=True) for o in observations] == [
        loaded.act(o, deterministic=True) for o in observations
    ]
    assert loaded.num_updates == agent.num_updates == 5


# ----------------------------------------------------------------------------- asynchronous


def test_actor_learner_training_updates_the_learner(tmp_path):
    reports = []
    config = IMPALAConfig(unroll_length=10, batch_size=2)
    trained = train_impala(
        CARTPOLE, *CARTPOLE_SPACES, config=config, total_steps=2000, num_actors=2, seed=0,
        callback=reports.append, start_method="forkserver",
    )
    agent = trained["agent_0"]
    assert isinstance(agent, IMPALA)
    assert not torch.equal(model_weights(agent), model_weights(IMPALA.from_spaces(*CARTPOLE_SPACES, config, seed=0)))
    assert reports[-1].env_steps == 2000  # counted by the learner, one unroll at a time
    assert agent.num_updates == 2000 // (10 * 2)
    assert {ep.worker for r in reports for ep in r.episodes} == {0, 1}  # both actors played
    lags = [r.metrics["agent_0"]["charts/policy_lag"] for r in reports if r.metrics]
    assert lags and min(lags) >= 0
    learning_rates = [r.metrics["agent_0"]["charts/learning_rate"] for r in reports if r.metrics]
    assert learning_rates == sorted(learning_rates, reverse=True) and learning_rates[-1] < 0.02 * config.learning_rate
    assert agent.optimizer.param_groups[0]["lr"] == config.learning_rate  # restored for in-process use
    assert live_pids(reports[-1].worker_pids) == []
    agent.save(tmp_path / "async.ckpt")
    loaded = agents.load(tmp_path / "async.ckpt")
    assert loaded.num_updates == agent.num_updates
    assert torch.equal(model_weights(loaded), model_weights(agent))


def test_actor_learner_multi_agent_keeps_one_network_per_agent():
    env_fn = functools.partial(MultiColourBar, [False, False], size=36)
    observation_space = gymnasium.spaces.Box(0, 255, (36, 36, 3), np.uint8)
    config = IMPALAConfig(unroll_length=8, batch_size=2)
    trained = train_impala(
        env_fn, observation_space, gymnasium.spaces.Discrete(3), ["agent_0", "agent_1"], config,
        total_steps=320, num_actors=2, seed=0, start_method="forkserver",
    )
    assert trained["agent_0"].num_updates >= 1 and trained["agent_1"].num_updates >= 1
    assert not torch.equal(model_weights(trained["agent_0"]), model_weights(trained["agent_1"]))


def test_a_raising_actor_surfaces_its_traceback_and_leaves_no_process():
    pids = []

    def record(progress):
        pids[:] = progress.worker_pids

    with pytest.raises(WorkerError, match="simulated simulator crash") as info:
        train_impala(
            functools.partial(Explodes, 200), *CARTPOLE_SPACES, total_steps=10**6, num_actors=2,
            callback=record, start_method="forkserver",
        )
    assert "in step" in info.value.worker_traceback
    assert pids and live_pids(pids) == []
    assert multiprocessing.active_children() == []


def test_keyboard_interrupt_in_the_callback_leaves_no_process():
    pids = []

    def interrupt(progress):
        pids[:] = progress.worker_pids
        if progress.env_steps > 500:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train_impala(CARTPOLE, *CARTPOLE_SPACES, total_steps=10**6, num_actors=2, callback=interrupt, start_method="forkserver")
    assert pids and live_pids(pids) == []
    assert multiprocessing.active_children() == []
