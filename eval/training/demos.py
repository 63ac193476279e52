"""Autopilot demonstrations in a replay learner's buffer (``cosim train --demo-steps N``).

Before a DQN, DDPG or TD3 run takes its first env step, :func:`demonstrate` drives the
run's own training env (same wrappers: frame stack, ``--obs``, action repeat, collision
and stall rules) with the scripted autopilot (cosim.controller.Autopilot; its Discrete(9)
quantisation for DQN) for whole episodes until at least N env steps are done, and hands
every AC's transitions to that AC's agent as demonstrations (Agent.observe_demonstration:
stored in its replay, not counted in its steps). The point is the turning slots: no
learner's own exploration had reached a turning goal on task version 3, so no goal reward
ever entered their replays (task version 3; in git history at 1b59d82, docs/results/2026-11-26-stall-pilot); the autopilot reaches
almost all of them. With ``--demo-updates K`` the learner then takes K gradient steps on
them alone (DQfD's pre-training, Hester et al. 2018); DQN's ``--set demo_margin=M`` adds
DQfD's large-margin loss, DDPG's and TD3's ``--set demo_bc=W`` a behaviour-cloning term on
them. What was driven is written to the run folder's ``demos.json``.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from tqdm import tqdm

from cosim.controller import Autopilot
from eval.training.config import TrainConfig

log = logging.getLogger(__name__)

DEMO_SEED = 900_000_000
"""First scenario seed of the demonstration episodes (cfg.seed added), far from the training
episodes' (seed + 100,003 k), the validation's and the test's, so no demonstration is a
held-out episode."""


def demonstrate(cfg: TrainConfig, build_agents, make_env, *, env_index: int = 0,
                progress: bool = False) -> tuple[dict, dict]:
    """Drive the autopilot in ``make_env(cfg, seed)`` for at least ``cfg.demo_steps`` env steps;
    each AC's transitions go to its agent's ``observe_demonstration`` as environment
    ``env_index``'s (a progress bar over the env steps with ``progress``). The agents come from
    ``build_agents(observation_space, action_space)`` (called once the env is open, so no second
    simulation is needed for its spaces: libsumo runs one per process) and must be prepared
    for the run's environments.

    Returns:
        The agents, and a summary: ``env_steps`` driven, ``episodes``, ``seconds``, and per
        AC its ``transitions`` and ``goals``.
    """
    repeat = cfg.agent_config.action_repeat
    discrete = cfg.action_type == "discrete"
    steps = episodes = 0
    start = time.monotonic()
    env = make_env(cfg, cfg.seed + DEMO_SEED)
    bar = tqdm(total=cfg.demo_steps, unit="step", desc=f"{cfg.env} {cfg.algo} demonstrations",
               dynamic_ncols=True, disable=not progress)
    try:
        agents = build_agents(env.observation_space("ac_0"), env.action_space("ac_0"))
        per_ac = {ac: {"transitions": 0, "goals": 0} for ac in agents}
        while steps < cfg.demo_steps:
            obs, _ = env.reset(seed=cfg.seed + DEMO_SEED + episodes)
            world = env.unwrapped.world
            pilots = {ac: Autopilot(world, ac) for ac in env.agents}
            while env.agents:
                actions = {ac: pilots[ac].act_discrete() if discrete else pilots[ac].act() for ac in env.agents}
                next_obs, rewards, terms, truncs, infos = env.step(actions)
                for ac, action in actions.items():
                    agents[ac].observe_demonstration(obs[ac], action, rewards[ac], next_obs[ac], terms[ac],
                                                     truncs[ac], column=env_index)
                    per_ac[ac]["transitions"] += 1
                    if terms[ac] or truncs[ac]:
                        per_ac[ac]["goals"] += bool(infos[ac].get("goal_reached"))
                obs = next_obs
                steps += repeat
                bar.update(min(repeat, max(cfg.demo_steps - bar.n, 0)))
            episodes += 1
    finally:
        bar.close()
        env.close()
    log.info("demonstrations: %d env steps in %d episodes (%.0f s), goals %s", steps, episodes,
             time.monotonic() - start, {ac: v["goals"] for ac, v in per_ac.items()})
    return agents, {"env_steps": steps, "episodes": episodes, "seconds": round(time.monotonic() - start, 1),
                    "agents": per_ac}


def pretrain(agents: dict, updates: int, progress: bool = False) -> dict[str, dict[str, float]]:
    """Pre-training on the demonstrations (``--demo-updates``): ``updates`` gradient steps
    per network (one for a run with shared parameters), under a progress bar with ``progress``
    (2,000 per AC took 12 minutes for 6 ACs on 2 busy cores: task version 3; in git history at 1b59d82, docs/results/2026-11-26-demo-pilot)."""
    from agents.shared import shared_core

    core = shared_core(agents)
    learners = {"shared": core} if core is not None else agents
    with tqdm(total=updates * len(learners), unit="update", desc="pre-training", dynamic_ncols=True,
              disable=not progress) as bar:
        return {name: agent.pretrain(updates, on_update=bar.update) for name, agent in learners.items()}


def record(run: Path, summary: dict) -> None:
    """Append one demonstration phase (a run resumed twice drives three) to ``run/demos.json``."""
    path = Path(run) / "demos.json"
    phases = json.loads(path.read_text()) if path.exists() else []
    phases.append(summary)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(phases, indent=1))
    tmp.replace(path)
