"""Checkpoints: round-trip gives identical actions; bad files raise CheckpointError."""

import numpy as np
import pytest
import torch

import agents
from agents.checkpoint import FORMAT, space_from_dict, space_to_dict
from agents.envs import ColourBar, SingleAgentParallel
from agents.loop import run_loop
from agents.ppo import PPO
from agents.registry import POLICY_NETWORKS, get_agent_class

from .conftest import FAST, GYM_ENV, SPACES

ALGOS = ["ppo", "dqn", "ddpg", "td3"]


def _trained(algo: str, steps: int = 100):
    import gymnasium as gym

    cls = get_agent_class(algo)
    agent = cls.from_spaces(*SPACES[algo], config=FAST[algo], seed=3)
    run_loop({"agent_0": agent}, SingleAgentParallel(gym.make(GYM_ENV[algo])), steps)
    return agent


@pytest.mark.parametrize("algo", ALGOS)
def test_round_trip_gives_identical_actions_and_state(algo, tmp_path):
    agent = _trained(algo)
    path = tmp_path / f"{algo}.pt"
    agent.save(path)
    loaded = agents.load(path)
    assert type(loaded) is type(agent) and loaded.config == agent.config
    assert loaded.observation_space == agent.observation_space
    assert loaded.action_space == agent.action_space
    rng = np.random.default_rng(0)
    for _ in range(20):
        obs = rng.normal(size=agent.observation_space.shape).astype(np.float32)
        np.testing.assert_array_equal(loaded.act(obs, deterministic=True), agent.act(obs, deterministic=True))
    # Optimizer state and counters come back too (so training can resume).
    for name, opt in agent.optimizers.items():
        assert loaded.optimizers[name].state_dict()["state"].keys() == opt.state_dict()["state"].keys()
    assert loaded.state_dict()["extra"] == agent.state_dict()["extra"]


@pytest.mark.parametrize("algo", ALGOS)
def test_a_policy_checkpoint_acts_like_the_full_one_and_holds_only_the_policy(algo, tmp_path):
    agent = _trained(algo)
    agent.save(tmp_path / "full.pt")
    agent.save(tmp_path / "policy.pt", policy_only=True)
    policy = agents.load(tmp_path / "policy.pt")
    assert policy.policy_only and not agents.load(tmp_path / "full.pt").policy_only
    rng = np.random.default_rng(1)
    for _ in range(20):
        obs = rng.normal(size=agent.observation_space.shape).astype(np.float32)
        np.testing.assert_array_equal(policy.act(obs, deterministic=True), agent.act(obs, deterministic=True))
    payload = torch.load(tmp_path / "policy.pt", weights_only=True)
    assert payload["kind"] == "policy" and payload["state"]["optimizers"] == {}
    assert tuple(payload["state"]["networks"]) == POLICY_NETWORKS[algo]
    assert (tmp_path / "policy.pt").stat().st_size < (tmp_path / "full.pt").stat().st_size / 2
    with pytest.raises(agents.CheckpointError, match="policy only"):
        agents.load(tmp_path / "policy.pt", require_full=True)


def _move_every_weight(agent, seed: int) -> None:
    """Every weight away from its initialisation, so that a network left out of a file shows."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for net in agent.networks.values():
            for p in net.parameters():
                p.add_(0.05 * torch.randn(p.shape, generator=gen))


@pytest.mark.parametrize("algo", ["ppo", "a3c", "impala", "dqn", "ddpg", "td3"])
def test_a_camera_policy_checkpoint_acts_like_the_full_agent(algo, tmp_path):
    """On camera images every network the action passes through is in the policy file: with
    every weight moved away from its initialisation, the policy-only agent acts as the full one
    (DDPG/TD3's actor reads the critic's CNN; a best.pt without the critic acted on untrained
    features)."""
    import gymnasium as gym

    cls = get_agent_class(algo)
    action = gym.spaces.Box(-1, 1, (2,), np.float32) if algo in ("ddpg", "td3") else gym.spaces.Discrete(9)
    agent = cls.from_spaces(gym.spaces.Box(0, 255, (84, 84, 3), np.uint8), action, seed=5)
    _move_every_weight(agent, seed=0)
    agent.save(tmp_path / "policy.pt", policy_only=True)
    policy = agents.load(tmp_path / "policy.pt")
    rng = np.random.default_rng(2)
    for _ in range(5):
        obs = rng.integers(0, 256, size=(84, 84, 3), dtype=np.uint8)
        np.testing.assert_allclose(policy.act(obs, deterministic=True), agent.act(obs, deterministic=True),
                                   rtol=0, atol=1e-6)


@pytest.mark.parametrize("algo", ["ppo", "a3c", "impala", "dqn", "ddpg", "td3"])
def test_every_policy_network_is_an_agent_network_and_the_camera_policy_fits_the_disk_budget(algo, tmp_path):
    """A quick run folder (6 ACs) keeps one policy file per AC: <= 60 MB needs <= 10 MB each."""
    import gymnasium as gym

    cls = get_agent_class(algo)
    action = gym.spaces.Box(-1, 1, (2,), np.float32) if algo in ("ddpg", "td3") else gym.spaces.Discrete(9)
    agent = cls.from_spaces(gym.spaces.Box(0, 255, (84, 84, 3), np.uint8), action)
    assert set(POLICY_NETWORKS[algo]) <= set(agent.networks)
    agent.save(tmp_path / "best.pt", policy_only=True)
    assert (tmp_path / "best.pt").stat().st_size <= 10e6


@pytest.mark.parametrize("algo", ["ppo", "ddpg"])
def test_a_float16_policy_file_is_half_the_size_and_acts_on_the_rounded_weights(algo, tmp_path):
    """policy_dtype float16 (the smoke preset's best.pt): about half the bytes; the loaded
    networks are float32 holding exactly the float16 rounding of the trained weights, so the
    policy acts as the trained agent would with rounded weights; a full checkpoint refuses it."""
    import gymnasium as gym

    cls = get_agent_class(algo)
    action = gym.spaces.Box(-1, 1, (2,), np.float32) if algo == "ddpg" else gym.spaces.Discrete(9)
    agent = cls.from_spaces(gym.spaces.Box(0, 255, (84, 84, 12), np.uint8), action, seed=3)
    _move_every_weight(agent, seed=1)
    agent.save(tmp_path / "f32.pt", policy_only=True)
    agent.save(tmp_path / "f16.pt", policy_only=True, policy_dtype="float16")
    assert (tmp_path / "f16.pt").stat().st_size < 0.6 * (tmp_path / "f32.pt").stat().st_size
    policy = agents.load(tmp_path / "f16.pt")
    for name in POLICY_NETWORKS[algo]:
        trained, loaded = agent.networks[name].state_dict(), policy.networks[name].state_dict()
        for key, value in trained.items():
            assert loaded[key].dtype == value.dtype
            expected = value.half().to(value.dtype) if value.is_floating_point() else value
            assert torch.equal(loaded[key], expected), (name, key)
    rounded = cls.from_spaces(agent.observation_space, action, seed=3)
    with torch.no_grad():
        for name, net in rounded.networks.items():
            for p, q in zip(net.parameters(), agent.networks[name].parameters(), strict=True):
                p.copy_(q.half().float())
    rng = np.random.default_rng(4)
    for _ in range(3):
        obs = rng.integers(0, 256, size=(84, 84, 12), dtype=np.uint8)
        np.testing.assert_allclose(policy.act(obs, deterministic=True), rounded.act(obs, deterministic=True),
                                   rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="full checkpoint keeps float32"):
        agent.save(tmp_path / "full16.pt", policy_dtype="float16")
    with pytest.raises(ValueError, match="policy_dtype must be one of float32, float16, got 'bf16'"):
        agent.save(tmp_path / "x.pt", policy_only=True, policy_dtype="bf16")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.int64, torch.uint8])
def test_packed_tensors_come_back_bit_for_bit(dtype):
    from agents.checkpoint import pack_tensor, unpack_tensor

    gen = torch.Generator().manual_seed(0)
    for shape in [(3136, 512), (32, 12, 8, 8), (7,), (), (0, 4)]:
        t = (torch.randn(shape, generator=gen) * 100).to(dtype)
        back = unpack_tensor(pack_tensor(t))
        assert back.dtype == t.dtype and back.shape == t.shape and torch.equal(back, t)
    weights = torch.randn(3136, 512, generator=gen) * 0.02  # float weights: exponents compress
    assert pack_tensor(weights)["data"].numel() < 0.95 * weights.numel() * 4


def test_image_round_trip_and_compact_space(tmp_path):
    env = ColourBar()
    agent = PPO.from_spaces(env.observation_space, env.action_space, FAST["ppo"])
    agent.save(tmp_path / "img.pt")
    payload = torch.load(tmp_path / "img.pt", weights_only=True)
    assert payload["format"] == FORMAT and payload["observation_space"]["low"] == 0
    assert set(payload["versions"]) == {"torch", "numpy", "cosim-agents"}
    obs, _ = env.reset(seed=1)
    assert agents.load(tmp_path / "img.pt").act(obs, True) == agent.act(obs, True)


def test_space_dict_round_trip():
    box = SPACES["td3"][1]
    assert space_from_dict(space_to_dict(box)) == box
    assert space_from_dict(space_to_dict(SPACES["dqn"][1])) == SPACES["dqn"][1]


def test_missing_file(tmp_path):
    with pytest.raises(agents.CheckpointError, match="does not exist"):
        agents.load(tmp_path / "nope.pt")


def test_truncated_and_garbage_files(tmp_path):
    path = tmp_path / "ok.pt"
    _trained("dqn", steps=10).save(path)
    data = path.read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(agents.CheckpointError, match="cut.pt.*truncated or corrupt"):
        agents.load(tmp_path / "cut.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint at all")
    with pytest.raises(agents.CheckpointError, match="junk.pt"):
        agents.load(tmp_path / "junk.pt")


def test_wrong_format_version_and_algorithm(tmp_path):
    torch.save({"weights": torch.zeros(2)}, tmp_path / "plain.pt")
    with pytest.raises(agents.CheckpointError, match="not a cosim agents checkpoint"):
        agents.load(tmp_path / "plain.pt")

    path = tmp_path / "dqn.pt"
    _trained("dqn", steps=10).save(path)
    with pytest.raises(agents.CheckpointError, match="holds a 'dqn' agent, not 'ppo'"):
        PPO.load(path)

    payload = torch.load(path, weights_only=True)
    payload["format_version"] = 99
    torch.save(payload, tmp_path / "future.pt")
    edited = {**payload, "format_version": 1, "seed": 12345}  # changed with its checksum kept: refused
    torch.save(edited, tmp_path / "edited.pt")
    with pytest.raises(agents.CheckpointError, match="edited.pt is corrupt: its contents do not match the checksum"):
        agents.load(tmp_path / "edited.pt")
    del payload["checksum"]  # the payloads below lack one, as files saved before checksums: loaded unchecked
    with pytest.raises(agents.CheckpointError, match="format version 99"):
        agents.load(tmp_path / "future.pt")

    payload["format_version"], payload["algo"] = 1, "rainbow"
    torch.save(payload, tmp_path / "unknown.pt")
    with pytest.raises(agents.CheckpointError, match="unknown algorithm 'rainbow'"):
        agents.load(tmp_path / "unknown.pt")

    payload["algo"] = "dqn"
    payload["observation_space"]["shape"] = (7,)
    torch.save(payload, tmp_path / "mismatch.pt")
    with pytest.raises(agents.CheckpointError, match="does not match"):
        agents.load(tmp_path / "mismatch.pt")


@pytest.mark.parametrize("algo", ["ppo", "a3c", "impala", "dqn", "ddpg", "td3"])
def test_retune_sets_config_and_learning_rates_and_keeps_weights_and_moments(algo, tmp_path):
    """PBT's explore step through the agents API: the checkpoint's config and every
    optimizer's learning rate change; weights and optimizer moments stay bit for bit."""
    import gymnasium as gym

    from agents.checkpoint import retune_checkpoint

    cls = get_agent_class(algo)
    if algo in SPACES:  # trained: its optimizers hold moments
        agent = _trained(algo)
    else:  # A3C and IMPALA train in their own loops (tests/agents/test_async*.py)
        agent = cls.from_spaces(gym.spaces.Box(0, 255, (84, 84, 3), np.uint8), gym.spaces.Discrete(9), seed=3)
    assert set(cls.optimizer_learning_rates) == set(agent.optimizers), "every optimizer has its rate field"
    agent.save(tmp_path / "latest.pt")
    agent.save(tmp_path / "best.pt", policy_only=True)
    before = torch.load(tmp_path / "latest.pt", weights_only=True)
    changes = {field: 0.5 * getattr(agent.config, field) for field in set(cls.optimizer_learning_rates.values())}
    new = agent.config.replace(**changes)
    for name in ("latest.pt", "best.pt"):
        retune_checkpoint(tmp_path / name, new)
    after = torch.load(tmp_path / "latest.pt", weights_only=True)
    assert after["config"] == new.to_dict()
    for net, tensors in before["state"]["networks"].items():
        for key, t in tensors.items():
            assert torch.equal(after["state"]["networks"][net][key], t), (net, key)
    for name, state in after["state"]["optimizers"].items():
        assert [g["lr"] for g in state["param_groups"]] == pytest.approx(
            [changes[cls.optimizer_learning_rates[name]]] * len(state["param_groups"]))
        old = before["state"]["optimizers"][name]["state"]
        for k, moments in state["state"].items():
            for key, value in moments.items():
                assert torch.equal(value, old[k][key]) if torch.is_tensor(value) else value == old[k][key]
    loaded = agents.load(tmp_path / "latest.pt", require_full=True)
    assert loaded.config == new
    assert {n: [g["lr"] for g in o.param_groups] for n, o in loaded.optimizers.items()} == {
        n: [changes[cls.optimizer_learning_rates[n]]] * len(o.param_groups) for n, o in loaded.optimizers.items()}
    assert agents.load(tmp_path / "best.pt").config == new
    other = get_agent_class("dqn" if algo != "dqn" else "ppo").config_class()
    with pytest.raises(agents.CheckpointError, match=f"holds a '{algo}' agent; retune it with a"):
        retune_checkpoint(tmp_path / "latest.pt", other)


@pytest.mark.parametrize("algo", ["ppo", "dqn", "td3"])
def test_warm_start_copies_the_policy_sets_targets_and_keeps_a_fresh_learner(algo, tmp_path):
    """`cosim train --init-from`: the policy networks come from the checkpoint (full or policy
    file), the target networks follow them, and the optimizer and counters stay fresh."""
    from agents.checkpoint import warm_start
    from agents.registry import TARGET_NETWORKS

    source = _trained(algo)
    source.save(tmp_path / "full.pt")
    source.save(tmp_path / "policy.pt", policy_only=True)
    for name in ("full.pt", "policy.pt"):
        fresh = get_agent_class(algo).from_spaces(*SPACES[algo], config=FAST[algo], seed=11)
        before = {k: [t.clone() for t in net.state_dict().values()] for k, net in fresh.networks.items()}
        warm_start(fresh, tmp_path / name)
        for net in POLICY_NETWORKS[algo]:
            for key, tensor in fresh.networks[net].state_dict().items():
                assert torch.equal(tensor, source.networks[net].state_dict()[key]), (name, net, key)
        for target, online in TARGET_NETWORKS[algo].items():
            assert not all(torch.equal(a, b) for a, b in
                           zip(before[target], fresh.networks[online].state_dict().values(), strict=True))
            for key, tensor in fresh.networks[target].state_dict().items():
                assert torch.equal(tensor, fresh.networks[online].state_dict()[key]), (target, key)
        assert fresh.steps == 0 < source.steps  # counters (epsilon, learning starts) start again
        assert all(not opt.state_dict()["state"] for opt in fresh.optimizers.values())


def test_warm_start_refuses_another_algorithm_or_other_spaces(tmp_path):
    import gymnasium as gym

    from agents.checkpoint import CheckpointError, warm_start

    _trained("dqn").save(tmp_path / "dqn.pt")
    ppo = get_agent_class("ppo").from_spaces(*SPACES["ppo"], config=FAST["ppo"], seed=0)
    with pytest.raises(CheckpointError, match="holds a 'dqn' agent, not 'ppo'"):
        warm_start(ppo, tmp_path / "dqn.pt")
    wider = gym.spaces.Box(-1.0, 1.0, (SPACES["dqn"][0].shape[0] + 1,), np.float32)
    other = get_agent_class("dqn").from_spaces(wider, SPACES["dqn"][1], config=FAST["dqn"], seed=0)
    with pytest.raises(CheckpointError, match="trained with observation_space .* same --obs"):
        warm_start(other, tmp_path / "dqn.pt")
