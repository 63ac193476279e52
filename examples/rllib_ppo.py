"""RLlib PPO (new API stack) on the multi-agent env, one policy shared by the ACs.

Needs the optional extra: ``pip install -e '.[ray]'``. The env goes through RLlib's
``ParallelPettingZooEnv``; the connector ``cosim.rllib.UInt8ToFloat`` casts the
uint8 images to float for RLlib's CNN encoder; ``reward_scale=0.01`` keeps values
inside PPO's ``vf_clip_param``.

    python examples/rllib_ppo.py --steps 256
"""

from __future__ import annotations

import argparse

import ray
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
from ray.tune.registry import register_env

import cosim
from cosim.rllib import UInt8ToFloat


def make_env(_config=None):
    return ParallelPettingZooEnv(cosim.parallel_env(
        "env_1", num_agents=2, background=False, pedestrians=False, horizon=64,
        reward_scale=0.01, image_size=42))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=256, help="env steps per training iteration")
    parser.add_argument("--iterations", type=int, default=1)
    args = parser.parse_args()

    # this machine only: Ray binds its ports to 127.0.0.1, as `cosim benchmark` does
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False, _node_ip_address="127.0.0.1")
    register_env("cosim_env_1", make_env)
    config = (
        PPOConfig()
        .environment("cosim_env_1")
        .env_runners(num_env_runners=0, rollout_fragment_length=args.steps // 2,
                     env_to_module_connector=lambda *a, **k: UInt8ToFloat())
        .multi_agent(policies={"shared"}, policy_mapping_fn=lambda agent_id, *a, **k: "shared")
        .training(train_batch_size_per_learner=args.steps, minibatch_size=args.steps // 2,
                  num_epochs=1, lr=3e-4)
        .rl_module(model_config={"conv_filters": [[16, [4, 4], 2], [32, [4, 4], 2], [64, [3, 3], 2]]})
    )
    algo = config.build_algo()
    for i in range(args.iterations):
        result = algo.train()
        learner = result.get("learners", {}).get("shared", {})
        print(f"iteration {i + 1}: env steps {result['num_env_steps_sampled_lifetime']}, "
              f"vf_loss {learner.get('vf_loss')}")
    algo.stop()
    ray.shutdown()
    print("done: RLlib PPO trained")


if __name__ == "__main__":
    main()
