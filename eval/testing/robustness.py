"""Cross-play and robustness sweeps of ``cosim test`` (issue 13): the episodes and their records
(the tables and figures: eval/reporting/robustness.py).

Cross-play (``--cross-play``): in each environment, the AC of one algorithm (the
*ego*, ``ac_0``) drives among ``group - 1`` ACs that all run one *partner* policy:
each other algorithm's AC, its own algorithm's (self-play) or the autopilot.

Robustness sweeps (``--sweep KIND=L1,L2,...``), Scenario 1 conditions, each level
a full set of episodes:

- ``density``: the background traffic's flow rates times the level (SUMO --scale);
- ``camera_noise``: Gaussian pixel noise of standard deviation level x 255;
- ``action_noise``: continuous actions + Gaussian noise of std level (clipped);
  discrete actions replaced by a random one with probability level;
- ``dropout``: each camera frame is lost with probability level (the policy sees
  the last frame it received).

The perturbations are seeded (plan seed, AC index): the same command gives the same
records.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd

from eval.testing.conditions import TestConditions, action_kinds
from eval.testing.protocol import ProtocolError
from eval.testing.rollout import AutopilotPolicy, run_episodes, use_cameras

SWEEP_KINDS = ("density", "camera_noise", "action_noise", "dropout")
def parse_sweeps(items: Sequence[str]) -> dict[str, list[float]]:
    """``["density=0.5,1,2"]`` -> ``{"density": [0.5, 1.0, 2.0]}``; ProtocolError when malformed."""
    out: dict[str, list[float]] = {}
    for item in items:
        kind, sep, levels = item.partition("=")
        if kind not in SWEEP_KINDS or not sep:
            raise ProtocolError(f"--sweep {item!r}: write KIND=L1,L2,... with KIND one of "
                                f"{', '.join(SWEEP_KINDS)}, e.g. --sweep density=0.5,1,2")
        try:
            values = [float(v) for v in levels.split(",") if v.strip()]
        except ValueError:
            raise ProtocolError(f"--sweep {item!r}: the levels must be numbers") from None
        bad = [v for v in values if v < 0 or (kind in ("dropout", "action_noise") and v > 1)
               or not np.isfinite(v)]
        if not values or bad:
            raise ProtocolError(f"--sweep {item!r}: give levels >= 0 (dropout and action_noise "
                                "at most 1)")
        out[kind] = values
    return out


class Perturbed:
    """A policy seen through a perturbation: noisy or lost camera frames, noisy actions."""

    def __init__(self, policy, space, kind: str, level: float, seed: int):
        self.policy, self.space, self.kind, self.level = policy, space, kind, float(level)
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.last = None

    @property
    def observes_camera(self) -> bool:
        from eval.testing.rollout import needs_camera

        return needs_camera(self.policy)  # a camera perturbation of a state policy perturbs nothing it reads

    def reset(self) -> None:
        if hasattr(self.policy, "reset"):
            self.policy.reset()
        self.last = None

    def act(self, obs, deterministic: bool = True):
        from eval.testing.rollout import _act

        if self.kind == "camera_noise" and self.level > 0:
            noise = self.rng.normal(0.0, self.level * 255.0, obs.shape)
            obs = np.clip(obs.astype(np.float32) + noise, 0, 255).astype(np.uint8)
        elif self.kind == "dropout":
            lost = self.last is not None and self.rng.random() < self.level
            obs = self.last if lost else obs
            self.last = obs
        action = _act(self.policy, obs)
        if self.kind == "action_noise" and self.level > 0:
            if hasattr(self.space, "n"):
                if self.rng.random() < self.level:
                    action = int(self.rng.integers(0, self.space.n))
            else:
                action = np.clip(np.asarray(action, np.float32)
                                 + self.rng.normal(0.0, self.level, 2).astype(np.float32), -1, 1)
        return action


def run_cross_play(plan, make_policy: Callable, algos: Sequence[str], group: int = 3,
                   progress: Callable[[str], None] | None = None) -> pd.DataFrame:
    """Records of every (ego, partner) pair in every environment of the plan."""
    partners = [*algos, "autopilot"]
    seeds = [plan.seed + e for e in range(plan.episodes)]
    frames = []
    for env_name in plan.envs:
        for ego in algos:
            for partner in partners:
                kinds = action_kinds([ego] + [partner] * (group - 1))
                env = TestConditions.of(1, plan.steps).env(env_name, kinds)
                try:
                    names = {a: (ego if i == 0 else partner) for i, a in enumerate(env.possible_agents)}
                    policies = {a: make_policy(env, a, ego) if i == 0 else
                                (AutopilotPolicy(env, a) if partner == "autopilot"
                                 else make_policy(env, a, partner))
                                for i, a in enumerate(env.possible_agents)}
                    use_cameras(env, policies)
                    rec = run_episodes(env, policies, seeds, algorithms=names)
                finally:
                    env.close()
                frames.append(rec.assign(env=env_name, scenario=1, ego=ego, partner=partner))
                if progress:
                    progress(f"{env_name} cross-play {ego} among {partner}")
    return pd.concat(frames, ignore_index=True)


def run_sweep(plan, make_policy: Callable, algos: Sequence[str], kind: str, levels: Sequence[float],
              progress: Callable[[str], None] | None = None) -> pd.DataFrame:
    """Scenario 1 records at every level of one perturbation."""
    from cosim.scenario import load_scenario

    algos = list(algos)[: plan.agents]
    seeds = [plan.seed + e for e in range(plan.episodes)]
    frames = []
    for level in levels:
        for env_name in plan.envs:
            sc = load_scenario(env_name)
            if kind == "density":
                sc = sc.with_overrides(background=dataclasses.replace(
                    sc.background, scale=sc.background.scale * level))
            env = TestConditions.of(1, plan.steps).env(sc, action_kinds(algos))
            try:
                names = dict(zip(env.possible_agents, algos, strict=True))
                policies = {}
                for i, a in enumerate(env.possible_agents):
                    p = make_policy(env, a, names[a])
                    if kind != "density":
                        p = Perturbed(p, env.action_space(a), kind, level, seed=plan.seed * 1000 + i)
                    policies[a] = p
                use_cameras(env, policies)
                rec = run_episodes(env, policies, seeds, algorithms=names)
            finally:
                env.close()
            frames.append(rec.assign(env=env_name, scenario=1, sweep=kind, level=float(level)))
            if progress:
                progress(f"{env_name} {kind}={level}")
    return pd.concat(frames, ignore_index=True)
