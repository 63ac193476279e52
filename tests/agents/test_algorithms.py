"""Each algorithm end to end: a few hundred steps on CartPole/Pendulum and the image task."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from agents.ddpg import DDPG, DDPGConfig
from agents.dqn import DQN, DQNConfig, linear_schedule
from agents.envs import ColourBar, SingleAgentParallel
from agents.loop import run_loop
from agents.ppo import PPO, PPOConfig
from agents.registry import get_agent_class
from agents.td3 import TD3, TD3Config

from .conftest import FAST, GYM_ENV, SPACES

ALGOS = ["ppo", "dqn", "ddpg", "td3"]


def _weights(agent) -> dict[str, torch.Tensor]:
    return {
        f"{n}.{k}": v.clone() for n, net in agent.networks.items() for k, v in net.state_dict().items()
    }


def _changed(before, agent) -> set[str]:
    after = _weights(agent)
    return {k for k in before if not torch.equal(before[k], after[k])}


@pytest.mark.parametrize("algo", ALGOS)
def test_runs_end_to_end_on_gym_task(algo):
    cls = get_agent_class(algo)
    env = SingleAgentParallel(gym.make(GYM_ENV[algo]))
    agent = cls.from_spaces(*SPACES[algo], config=FAST[algo], seed=0)
    before = _weights(agent)
    seen: list[dict[str, float]] = []
    stats = run_loop({"agent_0": agent}, env, 300, callback=lambda p: seen.extend(p.metrics.values()))
    assert stats.env_steps == 300 and stats.updates == len(seen) > 0
    assert all(np.isfinite(v) for metrics in seen for v in metrics.values())
    assert all(k.split("/")[0] in {"losses", "charts"} for k in seen[-1])
    assert stats.episode_returns["agent_0"], "an episode should have finished"
    changed = _changed(before, agent)
    # Online networks learn; DQN's target network is a copy of them.
    assert any(k.startswith(("net.", "q_network.", "actor.")) for k in changed)
    assert any(k.startswith(("net.", "q_network.", "critic.")) for k in changed)


@pytest.mark.parametrize("algo", ALGOS)
def test_runs_on_image_task(algo):
    env = ColourBar(continuous=algo in {"ddpg", "td3"}, size=36)
    cls = get_agent_class(algo)
    config = FAST[algo].replace(batch_size=8, **({"rollout_steps": 32} if algo == "ppo" else {"learning_starts": 16}))
    agent = cls.from_spaces(env.observation_space, env.action_space, config=config, seed=1)
    before = _weights(agent)
    stats = run_loop({"agent_0": agent}, SingleAgentParallel(env), 60)
    assert stats.updates > 0 and stats.episodes == 6
    assert agent.buffer.obs.dtype == np.uint8  # images stay uint8 in memory
    assert _changed(before, agent)


def test_epsilon_schedule_is_linear_then_constant():
    assert linear_schedule(1.0, 0.02, 100, 0) == 1.0
    assert linear_schedule(1.0, 0.02, 100, 50) == pytest.approx(0.51)
    assert linear_schedule(1.0, 0.02, 100, 1000) == pytest.approx(0.02)
    agent = DQN.from_spaces(*SPACES["dqn"], DQNConfig(exploration_steps=10, learning_starts=1000))
    obs = np.zeros(4, np.float32)
    for _ in range(5):
        agent.observe(obs, 0, 1.0, obs, False, False)
    assert agent.epsilon == pytest.approx(1.0 - 0.5 * 0.98)


def test_dqn_greedy_action_is_argmax_and_target_copies_on_schedule():
    agent = DQN.from_spaces(*SPACES["dqn"], DQNConfig(target_update_interval=3, learning_starts=10**6))
    obs = np.ones(4, np.float32)
    with torch.no_grad():
        expected = int(agent.q_network(torch.as_tensor(obs[None])).argmax())
    assert agent.act(obs, deterministic=True) == expected
    with torch.no_grad():
        next(agent.q_network.parameters()).add_(1.0)
    for step in range(1, 4):
        agent.observe(obs, 0, 0.0, obs, False, False)
        agent.update()
        synced = all(torch.equal(a, b) for a, b in zip(agent.q_network.parameters(), agent.target_network.parameters(), strict=True))
        assert synced == (step == 3)


def test_ppo_kl_coefficient_adapts_rllib_style():
    agent = PPO.from_spaces(*SPACES["ppo"], PPOConfig(rollout_steps=32, batch_size=8, epochs=1, kl_coef=0.3, kl_target=1e-9))
    obs = np.zeros(4, np.float32)
    for _ in range(32):
        a = agent.act(obs)
        agent.observe(obs, a, 1.0, obs, False, False)
    metrics = agent.update()
    # any policy change gives kl > 2 * 1e-9 -> coefficient grows by 1.5
    assert metrics["charts/kl_coef"] == pytest.approx(0.45)
    assert agent.update() == {}  # buffer was reset


def test_ppo_truncation_bootstraps_from_final_observation():
    agent = PPO.from_spaces(*SPACES["ppo"], PPOConfig(rollout_steps=4, batch_size=4))
    obs, final = np.zeros(4, np.float32), np.full(4, 3.0, np.float32)
    agent.act(obs)
    agent.observe(obs, 0, 1.0, final, terminated=False, truncated=True)
    expected = float(agent._values(final[None])[0])
    assert agent.buffer.next_values[0] == pytest.approx(expected) and expected != 0.0
    agent.act(obs)
    agent.observe(obs, 0, 1.0, final, terminated=True, truncated=False)
    assert agent.buffer.next_values[1] == 0.0


def test_ddpg_is_td3_with_tricks_off():
    cfg = DDPGConfig()
    assert (cfg.n_critics, cfg.policy_delay, cfg.target_policy_noise) == (1, 1, 0.0)
    assert issubclass(DDPG, TD3) and DDPG.algo == "ddpg"
    agent = DDPG.from_spaces(*SPACES["ddpg"])
    assert len(agent.critic.heads) == 1
    assert len(TD3.from_spaces(*SPACES["td3"]).critic.heads) == 2


def test_td3_actions_stay_in_bounds_and_warm_up_is_uniform():
    agent = TD3.from_spaces(*SPACES["td3"], TD3Config(learning_starts=100, exploration_noise=5.0))
    obs = np.zeros(3, np.float32)
    warm = np.array([agent.act(obs) for _ in range(100)])
    assert warm.min() >= -2 and warm.max() <= 2 and warm.std() > 0.9  # uniform on [-2, 2]: std 1.15
    agent.steps = 100
    noisy = np.array([agent.act(obs) for _ in range(50)])
    assert noisy.min() >= -2 and noisy.max() <= 2 and noisy.dtype == np.float32


@pytest.mark.parametrize("cls", [TD3, DDPG])
def test_random_phase_lasts_random_steps_draws_from_random_low_and_learning_starts_inside_it(cls):
    config = cls.config_class(learning_starts=20, random_steps=60, random_low=(1.0,), batch_size=8,
                              buffer_size=200)
    agent, twin = (cls.from_spaces(*SPACES[cls.algo], config, seed=3) for _ in range(2))
    obs = np.zeros(3, np.float32)
    drawn = []
    while agent.steps < 60:  # random until the 60th transition, from [1, 2] (Pendulum: [-2, 2])
        action = agent.act(obs)
        assert np.array_equal(action, twin.act(obs))  # seeded
        drawn.append(float(action[0]))
        batch = agent.act_batch(np.zeros((2, 3), np.float32), np.arange(2))
        assert np.array_equal(batch, twin.act_batch(np.zeros((2, 3), np.float32), np.arange(2)))
        assert batch.shape == (2, 1) and batch.min() >= 1.0
        agent.observe(obs, action, -1.0, obs, False, False)
        agent.update()
    assert min(drawn) >= 1.0 and max(drawn) <= 2.0 and np.std(drawn) > 0.2
    assert agent.gradient_updates > 0  # learning started at 20, inside the random phase
    agent.actor.mu.weight.data.zero_(), agent.actor.mu.bias.data.fill_(-5.0)  # the actor says -2
    assert agent.act(obs, deterministic=True)[0] == pytest.approx(-2.0, abs=1e-3)
    assert min(agent.act(obs)[0] for _ in range(20)) < 0  # past the phase: the actor's action


def test_random_steps_zero_keeps_the_learning_starts_warm_up_and_bad_floors_are_refused():
    agent = TD3.from_spaces(*SPACES["td3"], TD3Config(learning_starts=50))
    assert agent.random_until == 50 and np.array_equal(agent.random_low, agent.low)
    for floor in ((1.0, 1.0), (-3.0,), (2.0,)):  # wrong length, below low, not below high
        with pytest.raises(ValueError, match="random_low"):
            TD3.from_spaces(*SPACES["td3"], TD3Config(random_low=floor))
    with pytest.raises(ValueError, match="random_steps=.*valid range"):
        TD3Config(random_steps=-1)


@pytest.mark.parametrize(
    ("cls", "kwargs", "field"),
    [
        (PPOConfig, {"clip_coef": 0.0}, "clip_coef"),
        (PPOConfig, {"batch_size": 4096}, "batch_size"),
        (DQNConfig, {"exploration_final_eps": 1.5}, "exploration_final_eps"),
        (TD3Config, {"tau": 0.0}, "tau"),
        (DDPGConfig, {"policy_delay": 0}, "policy_delay"),
    ],
)
def test_config_validation_names_the_field(cls, kwargs, field):
    with pytest.raises(ValueError, match=f"{field}=.*valid range"):
        cls(**kwargs)


def test_presets_follow_spec_table_3():
    ppo = PPOConfig.preset("paper")
    assert (ppo.learning_rate, ppo.epochs, ppo.clip_coef, ppo.kl_coef, ppo.kl_target, ppo.gae_lambda) == (
        1e-3, 8, 0.3, 0.3, 0.03, 0.99)
    assert (ppo.batch_size, ppo.rollout_steps, ppo.gamma) == (128, 2048, 0.99)
    dqn = DQNConfig.preset("paper")
    assert (dqn.buffer_size, dqn.max_grad_norm, dqn.double_q) == (400, 40.0, False)
    assert DQNConfig.preset("default").buffer_size == 100_000
    assert (TD3Config.preset("paper").tau, DDPGConfig.preset("paper").tau) == (0.0002, 0.002)
    assert DDPGConfig.preset("paper").buffer_size == 500
    with pytest.raises(ValueError, match="valid presets"):
        PPOConfig.preset("fast")
    with pytest.raises(ValueError, match="unknown PPOConfig field"):
        PPOConfig.from_dict({"learning_rat": 1e-3})


def test_wrong_action_space_is_rejected():
    with pytest.raises(ValueError, match="Discrete"):
        PPO.from_spaces(*SPACES["td3"])
    with pytest.raises(ValueError, match="Box"):
        TD3.from_spaces(*SPACES["dqn"])
    agent = PPO.from_spaces(*SPACES["ppo"])
    with pytest.raises(ValueError, match="one observation at a time"):
        agent.act(np.zeros((2, 4), np.float32))


def test_same_seed_same_behaviour():
    runs = []
    for _ in range(2):
        agent = PPO.from_spaces(*SPACES["ppo"], FAST["ppo"], seed=7)
        stats = run_loop({"agent_0": agent}, SingleAgentParallel(gym.make("CartPole-v1")), 150, seed=7)
        runs.append(stats.episode_returns["agent_0"])
    assert runs[0] == runs[1]


def test_td3_image_actor_reads_the_critics_cnn_features():
    env = ColourBar(continuous=True, size=36)
    agent = TD3.from_spaces(env.observation_space, env.action_space, TD3Config(learning_starts=0))
    assert not any(isinstance(m, torch.nn.Conv2d) for m in agent.actor.modules())
    obs, _ = env.reset(seed=0)
    with torch.no_grad():
        expected = agent.actor(agent.critic.encode(torch.as_tensor(obs[None])))[0].numpy()
    np.testing.assert_allclose(agent.act(obs, deterministic=True), expected, rtol=1e-6)


@pytest.mark.parametrize("algo", ALGOS)
def test_reward_scale_multiplies_what_the_agent_learns_from(algo):
    obs_space, act_space = SPACES[algo]
    agent = get_agent_class(algo).from_spaces(obs_space, act_space, FAST[algo].replace(reward_scale=0.01))
    obs = np.zeros(obs_space.shape, np.float32)
    agent.observe(obs, agent.act(obs), 250.0, obs, terminated=False, truncated=False)
    assert agent.buffer.rewards[0] == pytest.approx(2.5)
    with pytest.raises(ValueError, match="reward_scale=0.*valid range"):
        FAST[algo].replace(reward_scale=0.0)


@pytest.mark.parametrize("penalty", [0.0, 1.0])
def test_td3_pre_tanh_penalty_pulls_a_saturated_actor_back(penalty):
    cfg = TD3Config(learning_starts=0, batch_size=16, buffer_size=100, policy_delay=1,
                    actor_learning_rate=0.05, pre_tanh_penalty=penalty)
    agent = TD3.from_spaces(*SPACES["td3"], cfg)
    with torch.no_grad():
        agent.actor.mu.bias.fill_(3.0)  # tanh(3) = 0.995: pinned at the upper bound
        for p in agent.critic.parameters():
            p.zero_()  # a flat critic: Q = 0 everywhere, no pull on the action
        agent.critic_target.load_state_dict(agent.critic.state_dict())
    obs = np.zeros(3, np.float32)
    for _ in range(32):
        agent.observe(obs, np.zeros(1, np.float32), 0.0, obs, terminated=False, truncated=False)
    metrics = [agent._gradient_step() for _ in range(30)]
    pre = agent.actor.preactivation(torch.zeros(1, 3)).item()
    assert metrics[0]["losses/actor_saturated"] == 1.0
    if penalty:
        assert pre < 2.0, "the penalty brings the actor out of saturation"
    else:
        assert pre == pytest.approx(3.0, abs=1e-3), "without it nothing moves a saturated actor"
