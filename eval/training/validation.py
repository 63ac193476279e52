"""Held-out validation episodes under the test's rules: how a training run picks the
checkpoint that represents each AC (docs/task.md, "Checkpoint selection").

At every checkpoint the run's ACs drive ``validation_episodes`` short episodes together, in
their own spawn slots, under the test protocol's rules: collisions do not end an episode,
each collision event is charged once (to the car at fault, docs/task.md "Collision rule"),
rewards unscaled, PPO, A3C and IMPALA sample their policy
and DQN, DDPG and TD3 act greedily (eval/testing/protocol.py), on seeds no training episode or test
uses (:func:`validation_seeds`). Each AC's score is its mean undiscounted return over those
episodes (``--select-by return``, the default) or its mean driving score (``--select-by ds``:
eval/testing/metrics.py score_of, the test's headline); its ``best.pt`` is the checkpoint with the
highest score so far (eval/training/runlog.py RunLog.checkpoint), and the run's
``selection.json`` records the rule, the seeds and every checkpoint's scores, both kinds.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np

from agents.registry import DETERMINISTIC, STOCHASTIC
from eval.training.config import TrainConfig

log = logging.getLogger(__name__)

VALIDATION_SEED = 1_999_000_000
"""First validation seed. Training episodes reset with ``seed + episode`` (+ 100,003 x the
episodes before a resume, below 10^9 for runs of under 10,000 episodes); the test protocol
uses ``--seed`` + episode and the validity suite 10,000 and up; SUMO takes seeds < 2^31."""

SCORED = {"ds": "mean driving score (ties to the later checkpoint)", "return": "mean undiscounted return"}
"""What each ``--select-by`` rule scores a checkpoint by (eval/training/options.py SELECTION_RULES)."""


def rule(select_by: str = "return") -> str:
    """The selection rule in words, as selection.json and the report say it."""
    return (f"per AC, the checkpoint with the highest {SCORED[select_by]} over the run's "
            "validation episodes, driven under the test's rules (collisions go on, each collision event "
            f"charged once; {', '.join(STOCHASTIC)} sample, {', '.join(DETERMINISTIC)} greedy) on "
            "held-out seeds; the run is represented by the AC with the highest such score")


RULE = rule("return")
"""The default rule in words."""


def validation_seeds(cfg: TrainConfig) -> list[int]:
    """The run's validation seeds: the same at every checkpoint, so scores compare."""
    return [VALIDATION_SEED + 100 * int(cfg.seed) + j for j in range(cfg.validation_episodes)]


class Validator:
    """Runs a config's validation episodes with the current weights of its ACs.

    The environment is built on first use and kept (:meth:`close` ends it); it runs beside
    the training environment (a second SUMO in one process runs in a child process: cosim/sumo_process.py).
    """

    def __init__(self, cfg: TrainConfig):
        self.cfg = cfg
        self.seeds = validation_seeds(cfg)
        self.steps = int(cfg.validation_steps)
        self._env = None

    def _make_env(self):
        from eval.testing.conditions import TestConditions
        from eval.training.encoder import observation

        cfg = self.cfg
        # the run's own action kind (--action-type), one per AC: the ACs under validation
        env = TestConditions.of(1, self.steps).env(cfg.env, cfg.action_type, cfg.agents,
                                                    seed=self.seeds[0], image_size=cfg.image_size)
        return observation(env, cfg)  # the run's own (its frozen encoder's features too)

    def both(self, agents: Mapping[str, object]) -> dict[str, dict[str, float]]:
        """Each AC's mean driving score and mean return over the validation episodes, as the
        test computes them (eval/testing/metrics.py episode_metrics): ``{"ds": {ac: DS},
        "return": {ac: return}}`` from one set of episodes; the run's rule reads its own."""
        from eval.testing.metrics import episode_metrics
        from eval.testing.protocol import SAMPLED
        from eval.testing.rollout import SampledPolicy, run_episodes

        if self._env is None:
            self._env = self._make_env()
        policies = {}
        for aid, agent in agents.items():
            sample = self.cfg.algo in SAMPLED
            policies[aid] = SampledPolicy(agent, int(aid.rsplit("_", 1)[1])) if sample else agent
        # act() is a batch of one outside any env column: it leaves what training keeps alone
        records = run_episodes(self._env, policies, self.seeds)
        means = episode_metrics(records, float(self._env.unwrapped.scenario.dt)).groupby("agent")[["return", "DS"]].mean()
        return {key: {aid: float(means[col].get(aid, np.nan)) for aid in agents}
                for key, col in (("return", "return"), ("ds", "DS"))}

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None
