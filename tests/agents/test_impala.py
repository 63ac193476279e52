"""Tests of IMPALA (agents/impala.py): config, V-trace loss, in-process and actor-learner training.

The actor-learner runs on the vector env (agents/vector.py): scripted envs whose
observations encode env, agent and step check the per-(env, agent) unrolls across
auto-resets, and recorded weights check that V-trace gets the acting policy's
log-probs. The learning benchmark (CartPole >= 475) lives in
bench/agents_async_reference.py; these tests run in seconds. Signals sent to a
training process are tested in tests/agents/test_workers.py.
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
from agents.envs import MultiColourBar, ScriptedParallelEnv, SingleAgentParallel
from agents.impala import IMPALA, IMPALAConfig, impala_loss, train_impala
from agents.loop import run_loop
from agents.workers import Rollout, RolloutBuilder, WorkerError, live_pids, private_copy

from .conftest import CARTPOLE, CARTPOLE_SPACES, model_weights


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


# ----------------------------------------------------------------------------- actor-learner on the vector env

SCRIPTED_SPACES = (gymnasium.spaces.Box(-np.inf, np.inf, (5,), np.float32), gymnasium.spaces.Discrete(3))


def _scripted(n: int, num_agents: int = 3, lengths=(3, 5, 4)):
    return [functools.partial(ScriptedParallelEnv, i, num_agents=num_agents, lengths=lengths) for i in range(n)]


def _capture_batches(monkeypatch) -> list[tuple[str, Rollout, torch.Tensor, torch.Tensor]]:
    """Record every learner step: (agent's first obs agent index, batch, weights before, weights after)."""
    batches = []
    learn = IMPALA.learn

    def recording(self, trajectories):
        before = model_weights(self)
        metrics = learn(self, trajectories)
        batches.append((self, Rollout.concat(trajectories), before, model_weights(self)))
        return metrics

    monkeypatch.setattr(IMPALA, "learn", recording)
    return batches


def test_learner_on_two_env_processes_updates_and_leaves_no_process(tmp_path):
    reports = []
    config = IMPALAConfig(unroll_length=10, batch_size=2)
    trained = train_impala(
        CARTPOLE, *CARTPOLE_SPACES, config=config, total_steps=2000, num_envs=2, seed=0,
        callback=reports.append, start_method="forkserver",
    )
    agent = trained["agent_0"]
    assert isinstance(agent, IMPALA)
    assert not torch.equal(model_weights(agent), model_weights(IMPALA.from_spaces(*CARTPOLE_SPACES, config, seed=0)))
    assert reports[-1].env_steps == 2000  # one step per env of a group, all counted
    assert agent.num_updates == 2000 // (10 * 2)  # every (env, agent) unroll is learnt from
    assert {ep.worker for r in reports for ep in r.episodes} == {0, 1}  # both environments played
    assert len(reports[-1].worker_pids) == 2
    lags = [r.metrics["agent_0"]["charts/policy_lag"] for r in reports if r.metrics]
    assert lags and min(lags) >= 0 and max(lags) > 0  # double buffering: actions lag the weights
    learning_rates = [r.metrics["agent_0"]["charts/learning_rate"] for r in reports if r.metrics]
    assert learning_rates == sorted(learning_rates, reverse=True) and learning_rates[-1] < 0.02 * config.learning_rate
    assert agent.progress_remaining == 0.0  # what the loop set before the last update: the budget spent
    assert live_pids(reports[-1].worker_pids) == []
    agent.save(tmp_path / "async.ckpt")
    loaded = agents.load(tmp_path / "async.ckpt")
    assert loaded.num_updates == agent.num_updates
    assert torch.equal(model_weights(loaded), model_weights(agent))


def test_unrolls_are_per_env_and_agent_with_true_final_observations(monkeypatch):
    batches = _capture_batches(monkeypatch)
    seed, n = 4, 3
    config = IMPALAConfig(unroll_length=4, batch_size=2)
    train_impala(_scripted(n), *SCRIPTED_SPACES, [f"agent_{k}" for k in range(3)], config,
                 total_steps=60 * n, seed=seed, processes=False)
    assert {agent.generator for agent, *_ in batches} and len(batches) >= 3
    for _agent, batch, *_ in batches:
        k = int(batch.obs[0, 1])
        assert (batch.obs[:, 1] == k).all(), "a batch mixes agents"
        assert len(batch) == 2 * config.unroll_length
        final = dict(zip(batch.final_index.tolist(), batch.final_obs, strict=True))
        for t in range(len(batch)):
            env, step, ep_seed = batch.obs[t, 0], batch.obs[t, 2], batch.obs[t, 3]
            nxt = final[t] if t in final else batch.obs[t + 1]
            # the observation after step t: same env, same agent, same episode, one step on
            assert (nxt[0], nxt[1], nxt[2], nxt[3]) == (env, k, step + 1, ep_seed)
            assert nxt[4] == batch.actions[t]
            assert batch.rewards[t] == pytest.approx(config.reward_scale * (nxt[2] + 100 * env + 10 * k))
            ends = nxt[2] == (3, 5, 4)[k] + ep_seed % 3
            assert bool(batch.dones[t]) == ends and bool(batch.terminateds[t]) == (ends and k % 2 == 0)
            if ends:
                assert t in final, "an episode end must keep its true final observation"
            if t not in final:  # inside an unroll: the next row is the next step
                assert (t + 1) % config.unroll_length != 0
    envs_seen = {(int(b.obs[0, 1]), int(e)) for _, b, *_ in batches for e in np.unique(b.obs[:, 0])}
    assert envs_seen == {(k, e) for k in range(3) for e in range(n)}


def test_vtrace_gets_the_behaviour_log_probs_of_the_acting_weights(monkeypatch):
    # One env, one agent, batches of one unroll: unroll j >= 1 was acted with the weights
    # before update j - 1 for its first step (chosen before that update) and with the
    # weights before update j for the rest.
    batches = _capture_batches(monkeypatch)
    config = IMPALAConfig(unroll_length=5, batch_size=1, learning_rate=1e-2)
    reports = []
    trained = train_impala(_scripted(1, num_agents=1, lengths=(7,)), *SCRIPTED_SPACES, ["agent_0"], config,
                           total_steps=60, seed=0, processes=False, callback=reports.append)
    agent = trained["agent_0"]
    assert len(batches) == 60 // 5

    def log_probs_under(weights: torch.Tensor, batch: Rollout) -> np.ndarray:
        model = private_copy(agent.model)
        torch.nn.utils.vector_to_parameters(weights, model.parameters())
        with torch.no_grad():
            logits, _ = model(torch.as_tensor(batch.obs))
        return torch.log_softmax(logits, -1).gather(1, torch.as_tensor(batch.actions)[:, None]).squeeze(1).numpy()

    np.testing.assert_allclose(batches[0][1].log_probs, log_probs_under(batches[0][2], batches[0][1]), atol=1e-5)
    for j in range(1, len(batches)):
        batch, before = batches[j][1], batches[j][2]
        previous = batches[j - 1][2]
        np.testing.assert_allclose(batch.log_probs[1:], log_probs_under(before, batch)[1:], atol=1e-5)
        np.testing.assert_allclose(batch.log_probs[0], log_probs_under(previous, batch)[0], atol=1e-5)
        assert abs(batch.log_probs[0] - log_probs_under(before, batch)[0]) > 1e-6  # not the learner's own
    lags = [r.metrics["agent_0"]["charts/policy_lag"] for r in reports if r.metrics]
    assert lags == [0.0] + [1.0] * (len(batches) - 1)
    rhos = [r.metrics["agent_0"]["charts/mean_rho"] for r in reports if r.metrics]
    assert rhos[0] == pytest.approx(1.0, abs=1e-5) and any(abs(r - 1.0) > 1e-4 for r in rhos[1:])


def test_same_seed_and_envs_give_the_same_weights():
    def run(seed: int) -> torch.Tensor:
        config = IMPALAConfig(unroll_length=5, batch_size=2)
        trained = train_impala(CARTPOLE, *CARTPOLE_SPACES, config=config, total_steps=300, num_envs=2, seed=seed,
                               processes=False)
        return model_weights(trained["agent_0"])

    first = run(0)
    assert torch.equal(first, run(0))
    assert not torch.equal(first, run(1))


def test_multi_agent_keeps_one_network_per_agent():
    env_fn = functools.partial(MultiColourBar, [False, False], size=36)
    observation_space = gymnasium.spaces.Box(0, 255, (36, 36, 3), np.uint8)
    config = IMPALAConfig(unroll_length=8, batch_size=2)
    trained = train_impala(
        env_fn, observation_space, gymnasium.spaces.Discrete(3), ["agent_0", "agent_1"], config,
        total_steps=320, num_envs=2, seed=0, processes=False,
    )
    assert trained["agent_0"].num_updates >= 1 and trained["agent_1"].num_updates >= 1
    assert not torch.equal(model_weights(trained["agent_0"]), model_weights(trained["agent_1"]))


def test_old_checkpoint_configs_with_actor_fields_still_load():
    config = IMPALAConfig.from_dict({"unroll_length": 7, "actor_sync_every": 1, "queue_size": 32})
    assert config.unroll_length == 7
    with pytest.raises(ValueError, match="unknown IMPALAConfig field"):
        IMPALAConfig.from_dict({"queue_sise": 32})


def test_a_raising_env_surfaces_its_traceback_and_leaves_no_process():
    pids = []

    def record(progress):
        pids[:] = progress.worker_pids

    failing = [functools.partial(ScriptedParallelEnv, i, num_agents=1, lengths=(50,), fail_at=30) for i in range(2)]
    with pytest.raises(WorkerError, match="scripted failure in env 0 at step 30") as info:
        train_impala(failing, *SCRIPTED_SPACES, total_steps=10**6, callback=record, start_method="forkserver")
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
        train_impala(CARTPOLE, *CARTPOLE_SPACES, total_steps=10**6, num_envs=2, callback=interrupt,
                     start_method="forkserver")
    assert pids and live_pids(pids) == []
    assert multiprocessing.active_children() == []
