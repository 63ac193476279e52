"""cosim: a multi-agent urban driving benchmark for deep RL on SUMO + PyBullet.

    import cosim
    env = cosim.parallel_env("env_3", num_agents=6, action_types="discrete")
    single = cosim.single_env("env_1", background=False, pedestrians=False)
    gym_env = gymnasium.make("cosim/FourWay-v5")

Nothing here starts a simulator: SUMO and PyBullet start (and report a missing
install) when an environment is reset.
"""

from cosim.env import CosimParallelEnv, parallel_env
from cosim.scenario import available_scenarios, load_scenario
from cosim.single import GYM_IDS, SingleAgentEnv, register_envs, single_env
from cosim.version import TASK_VERSION  # the task's version history is there

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
