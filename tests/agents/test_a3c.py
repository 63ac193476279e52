"""Tests of A3C (agents/a3c.py): config, loss, in-process and asynchronous training.

The learning benchmark (CartPole >= 475) lives in bench/agents_async_reference.py;
these tests run in seconds: the loss moves the policy the right way, both modes
run end to end and change the weights, checkpoints round-trip, the learner
threads (one per environment of the vector env) each learn from their own
environment and update the shared model asynchronously, and no env process or
thread outlives a failure or an interrupt.
"""

from __future__ import annotations

import functools
import multiprocessing
import threading

import gymnasium
import numpy as np
import pytest
import torch

import agents
from agents.a3c import A3C, A3CConfig, SharedAdam, a3c_loss, train_a3c
from agents.envs import MultiColourBar, ScriptedParallelEnv, SingleAgentParallel
from agents.loop import run_loop
from agents.workers import RolloutBuilder, WorkerError, live_pids

from .conftest import CARTPOLE, CARTPOLE_SPACES, model_weights

# ----------------------------------------------------------------------------- config and loss


def test_paper_preset_matches_table_3():
    config = A3CConfig.preset("paper")
    assert (config.learning_rate, config.vf_coef, config.ent_coef) == (5e-3, 1.0, 0.01)
    assert not config.anneal_lr
    assert (config.gae_lambda, config.max_grad_norm, config.gamma) == (1.0, 30.0, 0.99)


def test_config_rejects_bad_values_with_the_field_name():
    with pytest.raises(ValueError, match="n_steps"):
        A3CConfig(n_steps=0)
    with pytest.raises(ValueError, match="gae_lambda"):
        A3CConfig.preset("paper", gae_lambda=1.5)


@pytest.mark.parametrize("reward, direction", [(10.0, 1), (-10.0, -1)])
def test_loss_step_moves_probability_with_the_advantage(reward, direction):
    agent = A3C.from_spaces(*CARTPOLE_SPACES, A3CConfig(ent_coef=0.0, vf_coef=0.0, learning_rate=1e-2))
    obs = np.array([0.1, -0.2, 0.05, 0.3], dtype=np.float32)
    builder = RolloutBuilder("a")
    builder.add(obs, 1, reward, obs, True, False)  # terminal: the return is just the reward
    rollout = builder.build()

    @torch.no_grad()
    def log_prob_of_action() -> float:
        logits, _ = agent.model(torch.as_tensor(obs[None]))
        return float(torch.log_softmax(logits, -1)[0, 1])

    before = log_prob_of_action()
    loss, metrics = a3c_loss(agent.model, rollout, agent.config)
    agent.optimizer.zero_grad()
    loss.backward()
    agent.optimizer.step()
    assert np.sign(log_prob_of_action() - before) == direction
    assert set(metrics) == {"losses/policy_loss", "losses/value_loss", "losses/entropy"}


def test_value_loss_uses_n_step_returns():
    agent = A3C.from_spaces(*CARTPOLE_SPACES, A3CConfig(gamma=0.5))
    builder = RolloutBuilder("a")
    obs = [np.full(4, i, dtype=np.float32) for i in range(3)]
    builder.add(obs[0], 0, 1.0, obs[1], False, False)
    builder.add(obs[1], 0, 2.0, obs[2], True, False)
    rollout = builder.build()
    with torch.no_grad():
        _, values = agent.model(torch.as_tensor(np.stack(obs[:2])))
    returns = np.array([1.0 + 0.5 * 2.0, 2.0])  # terminal at step 1: no bootstrap
    expected = 0.5 * np.mean((returns - values.numpy()) ** 2)
    _, metrics = a3c_loss(agent.model, rollout, agent.config)
    assert metrics["losses/value_loss"] == pytest.approx(expected, rel=1e-5)


def test_shared_adam_apply_gradients_is_an_adam_step():
    # Gradients computed elsewhere (a thread's local copy) step the shared weights exactly as Adam does.
    shared = A3C.from_spaces(*CARTPOLE_SPACES, seed=0)
    reference = A3C.from_spaces(*CARTPOLE_SPACES, seed=0)
    assert isinstance(shared.optimizer, SharedAdam)
    rng = np.random.default_rng(0)
    for lr in (1e-2, 3e-3, 1e-3):
        grads = [torch.as_tensor(rng.normal(size=p.shape), dtype=p.dtype) for p in shared.model.parameters()]
        shared.optimizer.apply_gradients(grads, lr)
        for p, g in zip(reference.model.parameters(), grads, strict=True):
            p.grad = g.clone()
        reference.optimizer.param_groups[0]["lr"] = lr
        reference.optimizer.step()
        torch.testing.assert_close(model_weights(shared), model_weights(reference), rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="gradients for"):
        shared.optimizer.apply_gradients(grads[:-1], 1e-3)


# ----------------------------------------------------------------------------- in-process


def test_in_process_trains_through_the_common_loop():
    config = A3CConfig(n_steps=5)
    agent = A3C.from_spaces(*CARTPOLE_SPACES, config, seed=1)
    before = model_weights(agent)
    stats = run_loop({"agent_0": agent}, SingleAgentParallel(CARTPOLE()), total_steps=300, seed=1)
    assert stats.updates == 300 // config.n_steps
    assert all(np.isfinite(v) for v in stats.last_metrics["agent_0"].values())
    assert not torch.equal(before, model_weights(agent))


def test_checkpoint_round_trip_gives_identical_actions(tmp_path):
    agent = A3C.from_spaces(*CARTPOLE_SPACES, A3CConfig(n_steps=5), seed=3)
    run_loop({"agent_0": agent}, SingleAgentParallel(CARTPOLE()), total_steps=100)
    agent.save(tmp_path / "a3c.ckpt")
    loaded = agents.load(tmp_path / "a3c.ckpt")
    assert isinstance(loaded, A3C) and loaded.config == agent.config
    observations = np.random.default_rng(0).normal(size=(50, 4)).astype(np.float32)
    assert [agent.act(o, deterministic=True) for o in observations] == [
        loaded.act(o, deterministic=True) for o in observations
    ]
    assert loaded.num_updates == agent.num_updates == 20


# ----------------------------------------------------------------------------- asynchronous (threads on the vector env)

SCRIPTED_SPACES = (gymnasium.spaces.Box(-np.inf, np.inf, (5,), np.float32), gymnasium.spaces.Discrete(3))


def test_async_training_on_two_env_processes_updates_the_shared_model(tmp_path):
    reports = []
    trained = train_a3c(
        CARTPOLE, *CARTPOLE_SPACES, config=A3CConfig(n_steps=10), total_steps=3000, num_envs=2,
        seed=0, callback=reports.append, start_method="forkserver",
    )
    agent = trained["agent_0"]
    untrained = A3C.from_spaces(*CARTPOLE_SPACES, A3CConfig(n_steps=10), seed=0)
    assert isinstance(agent, A3C)
    assert not torch.equal(model_weights(agent), model_weights(untrained))
    assert reports[-1].env_steps == 3000  # steps are claimed before they are taken: no overshoot
    assert {ep.worker for r in reports for ep in r.episodes} == {0, 1}  # both environments played
    assert len(reports[-1].worker_pids) == 2 and live_pids(reports[-1].worker_pids) == []
    learnt = [r for r in reports if r.metrics]
    # one shared step per segment of 10 transitions; each thread may end within a segment
    assert agent.num_updates == len(learnt) and 3000 // 10 - 2 <= len(learnt) <= 3000 // 10
    learning_rates = [r.metrics["agent_0"]["charts/learning_rate"] for r in learnt]
    assert learning_rates[0] > learning_rates[-1] and learning_rates[-1] < 0.02 * agent.config.learning_rate
    agent.save(tmp_path / "async.ckpt")
    loaded = agents.load(tmp_path / "async.ckpt")
    observations = np.random.default_rng(1).normal(size=(20, 4)).astype(np.float32)
    assert [loaded.act(o, deterministic=True) for o in observations] == [
        agent.act(o, deterministic=True) for o in observations
    ]


def test_threads_apply_their_updates_asynchronously(monkeypatch):
    # Each thread computes its gradients on its own env's segments with weights it read
    # before the segment; updates of the other thread land in between (staleness > 0).
    import agents.a3c as a3c_module

    segments = []
    compute = a3c_module.compute_gradients

    def recording(model, rollout, config):
        segments.append((threading.current_thread().name, rollout))
        return compute(model, rollout, config)

    monkeypatch.setattr(a3c_module, "compute_gradients", recording)
    reports = []
    envs = [functools.partial(ScriptedParallelEnv, i, num_agents=1, lengths=(6,)) for i in range(3)]
    train_a3c(envs, *SCRIPTED_SPACES, config=A3CConfig(n_steps=4), total_steps=600, seed=2,
              callback=reports.append, processes=False)
    by_thread: dict[str, set] = {}
    for name, rollout in segments:
        assert len(set(rollout.obs[:, 0].tolist())) == 1, "a segment mixes environments"
        by_thread.setdefault(name, set()).add(int(rollout.obs[0, 0]))
    assert by_thread == {f"cosim-actor-{k}": {k} for k in range(3)}  # thread k owns env k
    staleness = [r.metrics["agent_0"]["charts/staleness"] for r in reports if r.metrics]
    assert 600 // 4 - 3 <= len(staleness) <= 600 // 4 and max(staleness) > 0


def test_segments_follow_each_env_across_auto_resets(monkeypatch):
    import agents.a3c as a3c_module

    segments = []
    compute = a3c_module.compute_gradients
    monkeypatch.setattr(a3c_module, "compute_gradients",
                        lambda model, rollout, config: (segments.append(rollout), compute(model, rollout, config))[1])
    envs = [functools.partial(ScriptedParallelEnv, i) for i in range(2)]
    ids = ["agent_0", "agent_1", "agent_2"]
    train_a3c(envs, *SCRIPTED_SPACES, ids, A3CConfig(n_steps=5), total_steps=200, seed=7, processes=False)
    # obs: (env, agent index, t, episode seed, last action)
    assert {(int(r.obs[0, 1]), int(r.obs[0, 0])) for r in segments} == {(k, e) for k in range(3) for e in range(2)}
    for rollout in segments:
        k = int(rollout.obs[0, 1])
        assert (rollout.obs[:, 1] == k).all(), "a segment mixes agents"
        final = dict(zip(rollout.final_index.tolist(), rollout.final_obs, strict=True))
        assert len(rollout) - 1 in final
        for t in range(len(rollout)):
            nxt = final[t] if t in final else rollout.obs[t + 1]
            assert tuple(nxt[:4]) == (rollout.obs[t, 0], k, rollout.obs[t, 2] + 1, rollout.obs[t, 3])
            ends = nxt[2] == (3, 5, 4)[k] + nxt[3] % 3
            assert bool(rollout.dones[t]) == ends and (not ends or t in final)


def test_one_environment_is_reproducible():
    def run(seed: int) -> torch.Tensor:
        trained = train_a3c(CARTPOLE, *CARTPOLE_SPACES, config=A3CConfig(n_steps=5), total_steps=200,
                            num_envs=1, seed=seed)
        return model_weights(trained["agent_0"])

    first = run(0)
    assert torch.equal(first, run(0)) and not torch.equal(first, run(1))


def test_async_multi_agent_trains_one_network_per_agent():
    env_fn = functools.partial(MultiColourBar, [False, False], size=36)
    observation_space = gymnasium.spaces.Box(0, 255, (36, 36, 3), np.uint8)
    ids = ["agent_0", "agent_1"]
    trained = train_a3c(
        env_fn, observation_space, gymnasium.spaces.Discrete(3), ids, A3CConfig(n_steps=8),
        total_steps=400, num_envs=2, seed=0, processes=False,
    )
    assert set(trained) == set(ids)
    for k, aid in enumerate(ids):
        untrained = A3C.from_spaces(observation_space, gymnasium.spaces.Discrete(3), A3CConfig(n_steps=8), seed=k)
        assert not torch.equal(model_weights(trained[aid]), model_weights(untrained)), aid
    assert not torch.equal(model_weights(trained["agent_0"]), model_weights(trained["agent_1"]))


def test_a_raising_env_surfaces_its_traceback_and_leaves_no_process():
    pids = []

    def record(progress):
        pids[:] = progress.worker_pids

    failing = [functools.partial(ScriptedParallelEnv, i, num_agents=1, lengths=(50,), fail_at=30) for i in range(2)]
    with pytest.raises(WorkerError, match="scripted failure in env") as info:
        train_a3c(failing, *SCRIPTED_SPACES, config=A3CConfig(n_steps=5), total_steps=10**6, callback=record,
                  start_method="forkserver")
    assert "in step" in info.value.worker_traceback  # the frame inside the env worker
    assert pids and live_pids(pids) == []
    assert multiprocessing.active_children() == []
    assert not [t for t in threading.enumerate() if t.name.startswith("cosim-actor")]


def test_keyboard_interrupt_in_the_callback_leaves_no_process_or_thread():
    pids = []

    def interrupt(progress):
        pids[:] = progress.worker_pids
        if progress.env_steps > 500:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train_a3c(CARTPOLE, *CARTPOLE_SPACES, total_steps=10**6, num_envs=2, callback=interrupt,
                  start_method="forkserver")
    assert pids and live_pids(pids) == []
    assert multiprocessing.active_children() == []
    assert not [t for t in threading.enumerate() if t.name.startswith("cosim-actor")]


def test_reward_scale_applies_to_a3c_and_impala_rollouts():
    from agents.impala import IMPALA, IMPALAConfig

    for cls, cfg in ((A3C, A3CConfig(n_steps=5, reward_scale=0.1)),
                     (IMPALA, IMPALAConfig(unroll_length=5, batch_size=1, reward_scale=0.1))):
        agent = cls.from_spaces(*CARTPOLE_SPACES, cfg)
        obs = np.zeros(4, np.float32)
        for reward in (10.0, -20.0):
            agent.observe(obs, agent.act(obs), reward, obs, terminated=False, truncated=False)
        builder = agent._builders[0] if cls is A3C else agent._unrolls.builders[("self", 0)]
        np.testing.assert_allclose(builder.build().rewards, [1.0, -2.0], rtol=1e-6)
