"""cosim: a multi-agent urban driving benchmark for deep RL on SUMO + PyBullet.

    import cosim
    env = cosim.parallel_env("env_3", num_agents=6, action_types="discrete")
    single = cosim.single_env("env_1", background=False, pedestrians=False)
    gym_env = gymnasium.make("cosim/FourWay-v4")

Nothing here starts a simulator: SUMO and PyBullet start (and report a missing
install) when an environment is reset.
"""

from cosim.env import CosimParallelEnv, parallel_env
from cosim.scenario import available_scenarios, load_scenario
from cosim.single import GYM_IDS, SingleAgentEnv, register_envs, single_env

TASK_VERSION = 4
"""The driving task's version, recorded in every run's manifest.json and every report's
provenance.json (``task_version``) so a results folder says which task it measured:

1. 2026-11-20 to 11-24: the paper's discrete steer fractions of a 35 degree wheel, no grip limit;
   training episodes ended at a collision; one camera frame; best.pt by training return.
2. since 2026-11-24 (issue 25; docs/task.md): the fractions of CARLA's 70 degree wheel with a
   grip limit; collisions go on and every contact step is charged, in training as in the test;
   4 stacked frames by default; best.pt by validation under the test's rules. Runs record
   the options that select variants (``--obs``, ``--frame-stack``, ``--collisions``,
   ``--share-params``) in their config.yaml.
3. since 2026-11-26: as 2, and SUMO's cars and people wait for an AC on their path through a
   junction (``SumoBridge.gate_entries``; docs/scenarios.md): background traffic no longer
   sets off into an AC that is still in the junction.
4. since 2026-12-01 (docs/task.md, "Collision rule" and "Driving score"): a contact is charged
   once per collision event (one per other actor within 5 s) and the episode goes on; a car
   ahead that an AC drives into is solid, as road objects are; SUMO's cars and people brake for
   an AC body in their path on a lane or not (``Scenario.cars_see_acs``); the test's headline
   metric is the driving score. The env ids carry the version (``cosim_v4``,
   ``cosim/FourWay-v4``), as Gymnasium and PettingZoo version an environment whose behaviour
   changed.
"""

__all__ = [
    "TASK_VERSION",
    "CosimParallelEnv",
    "GYM_IDS",
    "SingleAgentEnv",
    "available_scenarios",
    "load_scenario",
    "parallel_env",
    "register_envs",
    "single_env",
]

register_envs()  # cheap: only names entry points, starts no simulator
