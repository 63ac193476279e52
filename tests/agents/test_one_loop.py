"""One loop for every algorithm (issue 58): the six algorithms train through the same loop
function, agents.loop.run_loop, with the same callback type; the batch pair is each
algorithm's primitive; the trainer has one path on it."""

import ast
import functools
import inspect
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch

from agents import loop, registry
from agents.base import Agent
from agents.configs import A3CConfig, IMPALAConfig
from agents.envs import ScriptedParallelEnv, SingleAgentParallel
from agents.loop import Progress, run_loop
from agents.vector import InProcessVectorEnv

from .conftest import FAST

REPO_ROOT = Path(__file__).resolve().parents[2]
CONFIGS = {**FAST, "a3c": A3CConfig(n_steps=5), "impala": IMPALAConfig(unroll_length=5, batch_size=2)}


def _fake_env(algo: str, index: int = 0):
    """A simulator-free env: two agents with vector observations (Discrete actions), or
    Pendulum as a one-agent ParallelEnv (Box actions)."""
    if registry.get(algo).action == "continuous":
        return SingleAgentParallel(gymnasium.make("Pendulum-v1"))
    return ScriptedParallelEnv(index, num_agents=2, lengths=(3, 4))


def _weights(agent) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for net in agent.networks.values() for p in net.parameters()])


@pytest.mark.parametrize("algo", registry.available())
def test_every_algorithm_trains_through_run_loop_with_the_progress_callback(algo, monkeypatch):
    calls = []
    schedule = loop._schedule

    def counting(*args, **kwargs):  # every env step of every algorithm comes from this generator
        calls.append(algo)
        return schedule(*args, **kwargs)

    monkeypatch.setattr(loop, "_schedule", counting)
    reports: list[Progress] = []
    with InProcessVectorEnv([functools.partial(_fake_env, algo, i) for i in range(2)]) as venv:
        cls = registry.get_agent_class(algo)
        learners = {a: cls.from_spaces(venv.observation_space(a), venv.action_space(a), CONFIGS[algo], seed=k)
                    for k, a in enumerate(venv.possible_agents)}
        before = {a: _weights(agent) for a, agent in learners.items()}
        actors = registry.get_actors(algo)  # A3C: its actor-learner threads, one per env
        stats = run_loop(learners, venv, 400, callback=reports.append, seed=5,
                         actors=None if actors is None else actors(learners, 5))
    assert calls == [algo] * (2 if actors is not None else 1)  # the one schedule (per thread for A3C)
    assert reports and all(type(r) is Progress for r in reports)
    steps = [r.env_steps for r in reports]
    assert steps == sorted(steps) and steps[-1] == stats.env_steps == 400
    assert {e.worker for r in reports for e in r.episodes} == {0, 1}  # both environments played
    assert stats.episodes == len([e for r in reports for e in r.episodes]) > 0
    for a in learners:  # every AC learnt, on its own network, and said so in the progress record
        assert any(a in r.metrics for r in reports), (algo, a)
        assert not torch.equal(before[a], _weights(learners[a])), (algo, a)
        assert all(np.isfinite(v) for r in reports if a in r.metrics for v in r.metrics[a].values())


@pytest.mark.parametrize("algo", registry.available())
def test_act_and_observe_are_the_batch_pair_of_one_row(algo):
    cls = registry.get_agent_class(algo)
    for name in ("act", "observe"):  # derived once, in agents/base.py
        assert getattr(cls, name) is getattr(Agent, name), (algo, name)
    env = _fake_env(algo)
    spaces = env.observation_space("agent_0"), env.action_space("agent_0")
    agent, twin = (cls.from_spaces(*spaces, CONFIGS[algo], seed=3) for _ in range(2))
    obs = np.random.default_rng(0).normal(size=(4, *spaces[0].shape)).astype(np.float32)
    single = [agent.act(o, deterministic=True) for o in obs]
    batch = twin.act_batch(obs, None, deterministic=True)
    np.testing.assert_allclose(np.asarray(single, dtype=batch.dtype), batch, rtol=1e-5, atol=1e-6)
    continuous = registry.get(algo).action == "continuous"
    assert isinstance(single[0], int) != continuous  # an int for Discrete, an array for Box
    with pytest.raises(ValueError, match="one observation at a time"):
        agent.act(obs)


def _stepping_functions(path: Path) -> list[str]:
    """The functions of ``path`` that step a vector env: call ``<env>.step_wait(...)`` on
    something other than ``self`` (a vector env's own ``step`` is ``step_async`` + ``step_wait``)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.FunctionDef):
            continue
        for call in ast.walk(node):
            if (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute) and call.func.attr == "step_wait"
                    and not (isinstance(call.func.value, ast.Name) and call.func.value.id == "self")):
                found.append(node.name)
                break
    return found


def test_no_second_schedule_and_one_trainer_path():
    # only the loop's schedule steps environments in the product (A3C's threads run it too)
    stepping = [f"{path.relative_to(REPO_ROOT)}:{name}" for package in ("agents", "eval", "cosim", "studies")
                for path in sorted((REPO_ROOT / package).rglob("*.py")) for name in _stepping_functions(path)]
    assert stepping == ["agents/loop.py:_schedule"], stepping
    from eval.training import trainer

    assert not hasattr(trainer, "_train_sync") and not hasattr(trainer, "_train_async")
    source = inspect.getsource(trainer)
    assert source.count("run_loop(") == 1 and "get_async_trainer" not in source
    assert "7919" not in source and source.count("100_003") == 1  # one reseed rule
    assert source.count("runlog.checkpoint(") == 1  # one checkpoint rule
