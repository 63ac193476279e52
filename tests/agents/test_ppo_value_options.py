"""PPO's two options on the value loss (issue 59 item 2): ``shared_value_grad`` scales the value
loss's gradient into an encoder the policy shares, ``value_norm`` learns the returns in units of
their running statistics; with both off an update is the one before them, bit for bit."""

import functools

import numpy as np
import pytest
import torch
from torch import nn
from torch.distributions import Categorical, kl_divergence

from agents import observations
from agents.envs import MultiColourBar, ScriptedParallelEnv
from agents.loop import run_loop
from agents.networks import ActorCritic, obs_to_tensor
from agents.ppo import PPO, PPOConfig
from agents.returns import gae
from agents.vector import InProcessVectorEnv

CONFIG = PPOConfig(rollout_steps=48, batch_size=16, epochs=2, ent_coef=0.01)


class OldPPO(PPO):
    """PPO's acting and update as they were before issue 59 (commit 02b9d64), copied."""

    @torch.no_grad()
    def act_batch(self, obs, columns, deterministic=False):
        logits, values = self.net(obs_to_tensor(obs, self.device))
        if deterministic:
            actions = logits.argmax(-1)
        else:
            actions = torch.multinomial(torch.softmax(logits, -1), 1, generator=self.generator)[:, 0]
        log_probs = torch.log_softmax(logits, -1).gather(1, actions[:, None])[:, 0]
        actions_np, log_probs, values = actions.cpu().numpy(), log_probs.cpu().numpy(), values.cpu().numpy()
        logits = logits.cpu().numpy()
        for j, column in enumerate([] if columns is None else np.asarray(columns).tolist()):
            pending = self._column_cache.setdefault(column, __import__("collections").deque(maxlen=2))
            pending.append((int(actions_np[j]), float(log_probs[j]), float(values[j]), logits[j]))
        return actions_np

    def acting_chain(self, deterministic=False):
        return None  # always its own act_batch above

    @torch.no_grad()
    def _values(self, obs):
        return self.net(obs_to_tensor(obs, self.device))[1].cpu().numpy()

    def update(self):
        if not self.buffer.full:
            return {}
        cfg, buf = self.config, self.buffer
        n = buf.pos
        going_on = sorted(self._column_next)
        last_values = (self._values(observations.stack([self._column_next[c] for c in going_on]))
                       if going_on else [])
        next_values = buf.bootstrap_columns(dict(zip(going_on, np.asarray(last_values).tolist(), strict=True)))
        self._column_next.clear()
        advantages, returns = np.zeros(n, np.float32), np.zeros(n, np.float32)
        for idx in buf.column_indices():
            advantages[idx], returns[idx] = gae(
                buf.rewards[idx], buf.values[idx], next_values[idx], buf.terminateds[idx], buf.truncateds[idx],
                cfg.gamma, cfg.gae_lambda,
            )
        b_obs = obs_to_tensor(observations.take(buf.obs, slice(n)), self.device)
        b_actions = torch.as_tensor(buf.actions[:n], device=self.device)
        b_log_probs = torch.as_tensor(buf.log_probs[:n], device=self.device)
        b_logits = torch.as_tensor(buf.logits[:n], device=self.device)
        b_advantages = torch.as_tensor(advantages, device=self.device)
        b_returns = torch.as_tensor(returns, device=self.device)
        for _epoch in range(cfg.epochs):
            epoch_stats = []
            for mb in np.array_split(self.rng.permutation(n), max(1, n // cfg.batch_size)):
                mb = torch.as_tensor(mb, device=self.device)
                epoch_stats.append(self._minibatch_step(
                    observations.take(b_obs, mb), b_actions[mb], b_log_probs[mb], b_logits[mb],
                    b_advantages[mb], b_returns[mb]))
        pg_loss, v_loss, entropy, kl, clipfrac = np.mean(epoch_stats, axis=0)
        if kl > 2.0 * cfg.kl_target:
            self.kl_coef *= 1.5
        elif kl < 0.5 * cfg.kl_target:
            self.kl_coef *= 0.5
        self.iterations += 1
        self.buffer.reset()
        return {"losses/v_loss": float(v_loss)}

    def _minibatch_step(self, obs, actions, old_log_probs, old_logits, advantages, returns):
        cfg = self.config
        logits, values = self.net(obs)
        dist = Categorical(logits=logits)
        log_probs = dist.log_prob(actions)
        ratio = torch.exp(log_probs - old_log_probs)
        kl = kl_divergence(Categorical(logits=old_logits), dist).mean()
        if cfg.norm_adv and len(advantages) > 1:
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        pg_loss = torch.max(
            -advantages * ratio, -advantages * torch.clamp(ratio, 1 - cfg.clip_coef, 1 + cfg.clip_coef)
        ).mean()
        v_loss = 0.5 * ((values - returns) ** 2).mean()
        entropy = dist.entropy().mean()
        loss = pg_loss + self.kl_coef * kl + cfg.vf_coef * v_loss - cfg.ent_coef * entropy
        self.optimizer.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(self.net.parameters(), cfg.max_grad_norm)
        self.optimizer.step()
        clipfrac = ((ratio - 1.0).abs() > cfg.clip_coef).float().mean()
        return [pg_loss.item(), v_loss.item(), entropy.item(), kl.item(), clipfrac.item()]


def _vector_env(index: int):
    return ScriptedParallelEnv(index, num_agents=2, lengths=(5, 7))


def _image_env(index: int):
    return MultiColourBar([False, False], size=36, episode_length=6)


def _train(cls, make_env, config: PPOConfig, steps: int) -> dict:
    with InProcessVectorEnv([functools.partial(make_env, i) for i in range(2)]) as venv:
        learners = {a: cls.from_spaces(venv.observation_space(a), venv.action_space(a), config, seed=k)
                    for k, a in enumerate(venv.possible_agents)}
        run_loop(learners, venv, steps, seed=1)
    return learners


def _same_weights(a, b) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a.net.state_dict().values(), b.net.state_dict().values(), strict=True))


@pytest.mark.parametrize("make_env, steps", [(_vector_env, 200), (_image_env, 160)], ids=["vector", "image"])
def test_with_the_options_off_an_update_is_the_old_one_bit_for_bit(make_env, steps):
    assert (CONFIG.value_norm, CONFIG.shared_value_grad) == ("none", 1.0)  # the library's defaults
    old, new = _train(OldPPO, make_env, CONFIG, steps), _train(PPO, make_env, CONFIG, steps)
    for a in old:
        assert new[a].iterations == old[a].iterations >= 2
        assert _same_weights(new[a], old[a]), a
    # "shared" normalisation on separate value and policy MLPs (vectors) is no normalisation
    if make_env is _vector_env:
        shared = _train(PPO, make_env, CONFIG.replace(value_norm="shared"), steps)
        assert not shared["agent_0"].value_norm
        assert all(_same_weights(shared[a], old[a]) for a in old)
    else:  # ... and each option on, on the shared CNN, changes the update
        for changes in ({"value_norm": "shared"}, {"shared_value_grad": 0.25}):
            changed = _train(PPO, make_env, CONFIG.replace(**changes), steps)
            assert not _same_weights(changed["agent_0"], old["agent_0"]), changes


def test_shared_value_grad_scales_the_value_gradient_into_the_shared_encoder_only():
    torch.manual_seed(0)
    space = MultiColourBar([False], size=36).observation_space("agent_0")
    net = ActorCritic(space, 3)
    obs = torch.randint(0, 256, (8, 36, 36, 3), dtype=torch.uint8)
    target = torch.randn(8)
    grads, outputs = {}, {}
    for scale in (1.0, 0.25, 0.0):
        net.zero_grad()
        logits, values = net(obs, value_grad=scale)
        outputs[scale] = (logits.detach(), values.detach())
        (0.5 * (values - target).pow(2).mean()).backward()
        grads[scale] = {name: p.grad.clone() for name, p in net.named_parameters() if p.grad is not None}
    for scale in (0.25, 0.0):
        assert all(torch.equal(a, b) for a, b in zip(outputs[scale], outputs[1.0], strict=True))  # same values
        for name, g in grads[1.0].items():
            if name.startswith("encoder."):  # the shared CNN: the value's gradient times the scale
                if scale:
                    torch.testing.assert_close(grads[scale][name], scale * g, rtol=1e-5, atol=1e-9)
                else:
                    assert name not in grads[scale] or not grads[scale][name].any()
            elif name.startswith("value_head."):  # the value head learns from the whole loss
                assert torch.equal(grads[scale][name], g), name
    # separate encoders (vectors) ignore it
    vector = ActorCritic(_vector_env(0).observation_space("agent_0"), 3)
    x = torch.randn(4, 5)
    vector(x, value_grad=0.0)[1].sum().backward()
    assert vector.value_encoder.net[0].weight.grad.abs().sum() > 0


def test_value_norm_learns_the_returns_in_units_of_their_running_statistics(monkeypatch):
    seen_returns, seen_targets = [], []
    real_gae = gae

    def recording_gae(*args, **kwargs):
        out = real_gae(*args, **kwargs)
        seen_returns.append(out[1])
        return out

    def recording_losses(self, obs, actions, old_log_probs, old_logits, advantages, returns):
        seen_targets.append(returns.clone())
        return PPO.losses(self, obs, actions, old_log_probs, old_logits, advantages, returns)

    monkeypatch.setattr("agents.ppo.gae", recording_gae)
    config = CONFIG.replace(value_norm="all", epochs=1, reward_scale=25.0)  # returns far from unit scale
    env = ScriptedParallelEnv(0, num_agents=1, lengths=(6,))
    agent = PPO.from_spaces(env.observation_space("agent_0"), env.action_space("agent_0"), config, seed=0)
    monkeypatch.setattr(agent, "losses", recording_losses.__get__(agent))
    assert agent.value_norm and (agent.value_stats.mean, agent.value_stats.var) == (0.0, 1.0)
    run_loop({"agent_0": agent}, env, 10_000, callback=lambda progress: agent.iterations >= 1, seed=2)
    assert agent.iterations == 1 and len(seen_returns) == 1  # one environment: one GAE sequence
    returns = seen_returns[0]
    # the statistics: the returns' mean and variance (after the prior of weight 1e-4: mean 0, var 1)
    assert agent.value_stats.mean == pytest.approx(returns.mean(), rel=1e-3)
    assert agent.value_stats.var == pytest.approx(returns.var(), rel=1e-3)
    assert abs(returns.mean()) > 5 and returns.std() > 5  # far from unit scale: the test means something
    # the value head's targets: the returns in those units (one epoch: every row once)
    targets = torch.cat(seen_targets).numpy()
    want = ((returns - agent.value_stats.mean) / agent.value_stats.std).astype(np.float32)
    np.testing.assert_array_equal(np.sort(targets), np.sort(want))
    # acting keeps values in return units: the head's output times std plus mean
    obs = np.zeros((1, 5), np.float32)
    agent.act_batch(obs, np.array([7]))
    _, _, kept, _ = agent._column_cache[7][-1]
    with torch.no_grad():
        head = agent.net(torch.as_tensor(obs))[1].numpy()
    assert kept == pytest.approx(float(head[0] * agent.value_stats.std + agent.value_stats.mean), rel=1e-6)
    # and the statistics are saved with the agent
    state = agent.state_dict()
    twin = PPO.from_spaces(agent.observation_space, agent.action_space, config, seed=5)
    twin.load_state_dict(state)
    assert twin.value_stats.state() == agent.value_stats.state()


def test_the_options_are_checked():
    with pytest.raises(ValueError, match="value_norm"):
        PPOConfig(value_norm="yes")
    with pytest.raises(ValueError, match="shared_value_grad"):
        PPOConfig(shared_value_grad=1.5)
