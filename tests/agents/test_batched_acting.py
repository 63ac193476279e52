"""Acting in one grouped forward pass for several ACs (issue 59 item 1, agents/batched.py):
the same actions, the same kept log-probabilities and values, the same random streams and, in
training, the same weights as one forward pass per AC; the stacked weights follow every change;
``batched_acting=False`` is the per-AC path."""

import functools

import gymnasium
import numpy as np
import pytest
import torch

from agents import batched, observations, registry
from agents.configs import A3CConfig, IMPALAConfig
from agents.envs import MultiColourBar, ScriptedParallelEnv
from agents.loop import run_loop
from agents.networks import NatureCNN, scaled_image
from agents.vector import InProcessVectorEnv

from .conftest import FAST

IMAGE = gymnasium.spaces.Box(0, 255, (36, 36, 6), np.uint8)  # the smallest the Nature CNN takes, 2 frames
VECTOR = gymnasium.spaces.Box(-np.inf, np.inf, (12,), np.float32)
NAV = gymnasium.spaces.Dict({"image": IMAGE, "measurements": gymnasium.spaces.Box(-np.inf, np.inf, (5,), np.float32)})
DISCRETE = gymnasium.spaces.Discrete(5)
BOX = gymnasium.spaces.Box(np.array([-1.0, -2.0], np.float32), np.array([1.0, 0.5], np.float32))
CONFIGS = {**FAST, "a3c": A3CConfig(n_steps=5), "impala": IMPALAConfig(unroll_length=5, batch_size=2)}
# TD3/DDPG act with their networks from the first step (no random warm-up)
CONFIGS["td3"] = CONFIGS["td3"].replace(learning_starts=0)
CONFIGS["ddpg"] = CONFIGS["ddpg"].replace(learning_starts=0)
ALGOS = ("ppo", "dqn", "td3", "ddpg", "a3c", "impala")


def _agents(algo: str, space, n: int = 3, **changes) -> dict:
    cls = registry.get_agent_class(algo)
    actions = BOX if registry.get(algo).action == "continuous" else DISCRETE
    config = CONFIGS[algo].replace(**changes)
    return {f"ac_{k}": cls.from_spaces(space, actions, config, seed=10 + k) for k in range(n)}


def _obs(space, rows: int, rng) -> np.ndarray:
    if isinstance(space, gymnasium.spaces.Dict):  # the nav observation: frames and measurements
        return {key: _obs(sub, rows, rng) for key, sub in space.spaces.items()}
    if space.dtype == np.uint8:
        return rng.integers(0, 256, (rows, *space.shape), dtype=np.uint8)
    return rng.normal(size=(rows, *space.shape)).astype(np.float32)


def _streams(agent) -> tuple:
    """Where an agent's random streams stand: numpy's generator and torch's."""
    return agent.rng.bit_generator.state["state"]["state"], agent.generator.get_state().sum().item()


def _kept(agent) -> list:
    """What acting kept for learning: PPO's (action, log prob, value, logits), IMPALA's log mu."""
    pending = getattr(agent, "_column_cache", None) or getattr(agent, "_behaviour", None) or {}
    return [tuple(np.asarray(x).tobytes() for x in item) for c in sorted(pending) for item in pending[c]]


def _grouped_calls(monkeypatch) -> list:
    """Spy on GroupedNetworks: one entry per grouped pass that ran (not None)."""
    calls = []
    call = batched.GroupedNetworks.__call__

    def counting(self, x):
        out = call(self, x)
        if out is not None:
            calls.append(self.groups)
        return out

    monkeypatch.setattr(batched.GroupedNetworks, "__call__", counting)
    return calls


@pytest.mark.parametrize("space", [IMAGE, VECTOR, NAV], ids=["image", "vector", "nav"])
@pytest.mark.parametrize("algo", ALGOS)
def test_grouped_acting_gives_each_acs_actions_bit_for_bit(algo, space, monkeypatch):
    calls = _grouped_calls(monkeypatch)
    changes = {"exploration_initial_eps": 0.3} if algo == "dqn" else {}  # mostly greedy: the network decides
    alone, together = _agents(algo, space, **changes), _agents(algo, space, **changes)
    grouper, rng = batched.Grouper(), np.random.default_rng(0)
    for step in range(4):
        deterministic = step == 3
        rows = 1 + step % 2  # one env and two: the kernels are chosen per shape
        columns = np.arange(rows)
        requests = [(a, columns, _obs(space, rows, rng)) for a in alone]
        want = {a: alone[a].act_batch(obs, columns, deterministic=deterministic) for a, _, obs in requests}
        got = batched.act_all(together, requests, deterministic, grouper)
        for a in alone:
            assert got[a].dtype == want[a].dtype and np.array_equal(got[a], want[a]), (algo, step, a)
            assert _streams(together[a]) == _streams(alone[a]), (algo, step, a)  # each AC's own draws
            assert _kept(together[a]) == _kept(alone[a]), (algo, step, a)
        for a in alone:  # let what was kept go, as observe would
            for agent in (alone[a], together[a]):
                agent.prepare_envs(1)
    assert calls, "the grouped pass never ran"


@pytest.mark.parametrize("algo", ["dqn", "td3"])
def test_stacked_weights_follow_every_change_of_an_acs_weights(algo):
    alone, together = _agents(algo, IMAGE), _agents(algo, IMAGE)
    grouper, rng = batched.Grouper(), np.random.default_rng(1)

    def same(step) -> None:
        requests = [(a, None, _obs(IMAGE, 2, rng)) for a in alone]
        got = batched.act_all(together, requests, True, grouper)
        for a, _, obs in requests:
            assert np.array_equal(got[a], alone[a].act_batch(obs, None, deterministic=True)), (step, a)

    same("before")
    copies = grouper.copies
    same("nothing changed")
    assert grouper.copies == copies  # an AC that did not learn costs no copy
    other = registry.get_agent_class(algo).from_spaces(IMAGE, together["ac_1"].action_space, CONFIGS[algo], seed=99)
    for twins in (alone, together):  # a new network for ac_1: load_state_dict copies in place
        twins["ac_1"].load_state_dict(other.state_dict())
    same("after load_state_dict")
    changed = grouper.copies - copies
    stacked = sum(len(leaf.names) for found in grouper.groups.values() for net in found for leaf in net.leaves.values())
    assert changed == stacked > 0  # ac_1's stacked tensors (its large layers are never copied), no other AC's
    for twins in (alone, together):  # an optimiser-like in-place step, and a replaced tensor
        with torch.no_grad():
            next(iter(twins["ac_2"].acting_chain(True)[0].parameters())).mul_(1.5)
        last = list(twins["ac_0"].acting_chain(True)[-1].parameters())[-1]
        last.data = last.data + 0.25
        linear = [m for m in twins["ac_2"].acting_chain(True)[-1].modules() if isinstance(m, torch.nn.Linear)][-1]
        linear.bias = torch.nn.Parameter(linear.bias.detach() - 0.5)  # a new parameter object
    same("after an in-place step, a new tensor and a new parameter")


def _scripted(index: int):
    return ScriptedParallelEnv(index, num_agents=3, lengths=(5, 7, 6))


def _colour_bars(continuous: bool, index: int):
    return MultiColourBar([continuous] * 3, size=36, episode_length=6)


def _weights(agent) -> list[torch.Tensor]:
    return [t.detach().clone() for net in agent.networks.values() for t in (*net.parameters(), *net.buffers())]


def _train(algo: str, make_env, batched_acting: bool, steps: int) -> tuple[dict, dict, dict]:
    """Initial and final weights of 3 ACs trained ``steps`` env steps on 2 envs, and their returns."""
    with InProcessVectorEnv([functools.partial(make_env, i) for i in range(2)]) as venv:
        cls = registry.get_agent_class(algo)
        config = CONFIGS[algo].replace(batched_acting=batched_acting)
        if hasattr(config, "train_freq"):  # a gradient step per 4 transitions: a short test
            config = config.replace(train_freq=4, learning_starts=16)
        learners = {a: cls.from_spaces(venv.observation_space(a), venv.action_space(a), config, seed=k)
                    for k, a in enumerate(venv.possible_agents)}
        initial = {a: _weights(agent) for a, agent in learners.items()}
        stats = run_loop(learners, venv, steps, seed=3)
    return initial, {a: _weights(agent) for a, agent in learners.items()}, stats.episode_returns


@pytest.mark.parametrize("algo, env, steps", [
    ("ppo", _scripted, 240), ("dqn", _scripted, 120), ("a3c", _scripted, 120), ("impala", _scripted, 120),
    ("ppo", functools.partial(_colour_bars, False), 300), ("dqn", functools.partial(_colour_bars, False), 60),
    ("td3", functools.partial(_colour_bars, True), 40), ("ddpg", functools.partial(_colour_bars, True), 40),
], ids=["ppo-vector", "dqn-vector", "a3c-vector", "impala-vector", "ppo-image", "dqn-image", "td3-image",
        "ddpg-image"])
def test_training_with_batched_acting_on_and_off_gives_the_same_weights(algo, env, steps, monkeypatch):
    calls = _grouped_calls(monkeypatch)
    initial, off, returns_off = _train(algo, env, False, steps)
    assert not calls  # batched_acting=False: one forward pass per AC, the old path
    _, on, returns_on = _train(algo, env, True, steps)
    assert 3 in calls  # all three ACs acted together (two, once one had finished)
    assert returns_on == returns_off
    for a in off:
        assert len(on[a]) == len(off[a]) and all(torch.equal(x, y) for x, y in zip(on[a], off[a], strict=True)), a
        assert any(not torch.equal(x, y) for x, y in zip(on[a], initial[a], strict=True)), a  # it learnt


def test_shared_parameter_slots_act_on_the_old_path(monkeypatch):
    from agents.shared import share

    calls = _grouped_calls(monkeypatch)
    with InProcessVectorEnv([functools.partial(_scripted, i) for i in range(2)]) as venv:
        core = registry.get_agent_class("dqn").from_spaces(venv.observation_space("agent_0"),
                                                            venv.action_space("agent_0"), CONFIGS["dqn"], seed=0)
        run_loop(share(core, venv.possible_agents), venv, 40, seed=3)
    assert not calls


def test_scaled_image_is_the_old_conversion_bit_for_bit():
    torch.manual_seed(0)
    net = NatureCNN((36, 36, 6))
    images = torch.randint(0, 256, (5, 36, 36, 6), dtype=torch.uint8)
    old = images.float().permute(0, 3, 1, 2) / 255.0
    new = scaled_image(images)
    assert torch.equal(old, new) and old.stride() == new.stride()
    floats = images.float()
    assert torch.equal(scaled_image(floats), old) and torch.equal(floats, images.float())  # not scaled in place
    grads = []
    for x in (old, new):  # the same forward and backward through the CNN
        net.zero_grad()
        net.linear(net.cnn(x)).square().sum().backward()
        grads.append([p.grad.clone() for p in net.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(*grads, strict=True))


def test_an_architecture_without_a_grouped_form_acts_alone():
    agents = _agents("dqn", VECTOR)
    agents["ac_1"].q_network.encoder.net.append(torch.nn.Dropout(0.0))  # a module batched.py does not know
    grouper = batched.Grouper()
    assert grouper.key(agents["ac_1"], np.zeros((1, 12), np.float32), True) is None
    assert grouper.key(agents["ac_0"], np.zeros((1, 12), np.float32), True) is not None
    rng = np.random.default_rng(2)
    requests = [(a, None, _obs(VECTOR, 1, rng)) for a in agents]
    got = batched.act_all(agents, requests, True, grouper)
    for a, _, obs in requests:
        assert np.array_equal(got[a], agents[a].act_batch(obs, None, deterministic=True))
    assert observations.rows(requests[0][2]) == 1
