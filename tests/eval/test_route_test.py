"""The test drives a route-trained checkpoint on the route camera (`cosim train --obs route`): its
run folder's config.yaml says the variant (the checkpoint's observation space is the plain
camera's), and only the slot it drives gets its route drawn."""

import gymnasium
import numpy as np
import pytest
import yaml

from agents.registry import get_agent_class
from cosim.mirror import ROUTE_COLOR
from eval.testing.conditions import TestConditions
from eval.testing.loading import drive, load_for_slot
from eval.testing.protocol import ProtocolError


def _run(tmp_path, name: str, obs: str):
    """A run folder holding one DQN checkpoint on 84x84x3 frames; its config.yaml says ``obs``."""
    run = tmp_path / name
    ckpt = run / "checkpoints" / "ac_0" / "best.pt"
    ckpt.parent.mkdir(parents=True)
    cls = get_agent_class("dqn")
    space = gymnasium.spaces.Box(0, 255, (84, 84, 3), np.uint8)
    cls.from_spaces(space, gymnasium.spaces.Discrete(9), cls.config_class(), seed=0).save(ckpt, policy_only=True)
    (run / "config.yaml").write_text(yaml.safe_dump({"algo": "dqn", "env": "env_1", "obs": obs}))
    return ckpt


def _route_pixels(frame: np.ndarray) -> int:
    return int(np.all(frame == np.array(ROUTE_COLOR, np.uint8), axis=-1).sum())


def test_a_route_checkpoint_draws_only_its_own_slots_route(tmp_path):
    route = load_for_slot(_run(tmp_path, "env_1__dqn__0__route", "route"), "dqn")
    plain = load_for_slot(_run(tmp_path, "env_1__dqn__0__image", "image"), "dqn")
    assert route.draws_route and not plain.draws_route
    env = TestConditions.of(1, 5).env("env_1", ["discrete", "discrete"], seed=0)
    try:
        drive(plain, None, env, "ac_0"), drive(route, None, env, "ac_1")
        assert env.route_agents == {"ac_1"}
        obs, _ = env.reset(seed=0)
        assert _route_pixels(obs["ac_1"]) > 50 and _route_pixels(obs["ac_0"]) == 0
        with pytest.raises(ProtocolError, match="trained with --obs route: give drive\\(\\) the test env"):
            drive(route)
    finally:
        env.close()
