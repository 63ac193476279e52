"""`--stall-truncate N` (Termination.stall_truncate): a training episode is truncated once every
AC has stood still N steps away from a red light; off, the episode runs to the horizon."""

import dataclasses

import pytest
import yaml

from cosim.scenario import Termination, load_scenario
from cosim.world import World
from eval.training.config import TrainError, make_config
from eval.training.runfolder import load_run_config
from eval.training.trainer import make_env

BRAKE = (-1.0, 0.0)


def _world(stall_truncate: int, agents: int = 2, horizon: int = 120) -> World:
    sc = load_scenario("env_1")
    sc = sc.with_overrides(horizon=horizon,
                           termination=dataclasses.replace(sc.termination, stall_truncate=stall_truncate))
    return World(sc, agents, background=False, pedestrians=False)


def _brake_until_done(world: World, seed: int = 0):
    """Brake every AC until the episode ends; the step count and the last results."""
    world.reset(seed=seed)
    steps, last = 0, {}
    while world.active:
        last = world.step({a: BRAKE for a in world.active})
        steps += 1
    return steps, last


def test_braking_cars_are_truncated_n_steps_after_all_stand():
    with _world(stall_truncate=20) as w:
        w.reset(seed=0)
        steps, all_stand_at, last = 0, None, {}
        while w.active:
            last = w.step({a: BRAKE for a in w.active})
            steps += 1
            if all_stand_at is None and all(w.ac_state(a)[3] < 0.1 for a in w.ac_ids):
                all_stand_at = steps
    assert steps < 120, "the episode ended before the horizon"
    assert all(r.truncated and not r.terminated for r in last.values())
    assert all_stand_at > 1, "the cars had speed at the start (depart speed 7 m/s)"
    assert steps == all_stand_at + 19, "truncated on the 20th step on which every AC stood"


def test_off_the_same_cars_stand_to_the_horizon():
    with _world(stall_truncate=0) as w:
        steps, last = _brake_until_done(w)
    assert steps == 120
    assert all(r.truncated and not r.terminated for r in last.values())


def test_one_moving_ac_keeps_the_episode_going():
    with _world(stall_truncate=10) as w:
        w.reset(seed=0)
        for _ in range(60):  # ac_0 brakes and stands; ac_1 rolls on at a little throttle
            out = w.step({"ac_0": BRAKE, "ac_1": (0.2, 0.0)})
            assert not any(r.truncated for r in out.values())


def test_waiting_at_a_red_light_is_not_stalling(monkeypatch):
    with _world(stall_truncate=10) as w:
        monkeypatch.setattr(w.bridge, "next_tls", lambda ac: ("r", 12.0))
        w.reset(seed=0)
        for _ in range(60):
            assert not any(r.truncated for r in w.step({a: BRAKE for a in w.active}).values())
        monkeypatch.setattr(w.bridge, "next_tls", lambda ac: ("G", 12.0))  # green: now it stalls
        ended = [any(r.truncated for r in w.step({a: BRAKE for a in w.active}).values()) for _ in range(10)]
    assert ended == [False] * 9 + [True]


def test_a_red_light_far_ahead_does_not_excuse_standing(monkeypatch):
    with _world(stall_truncate=10) as w:
        monkeypatch.setattr(w.bridge, "next_tls", lambda ac: ("r", 80.0))
        steps, _ = _brake_until_done(w)
    assert steps < 120


@pytest.mark.parametrize("bad", [-1, True, 2.5])
def test_termination_refuses_a_bad_stall_count(bad):
    with pytest.raises(ValueError, match="stall_truncate"):
        Termination(stall_truncate=bad)


def test_train_option_reaches_the_env_and_old_configs_read_it_as_off(tmp_path):
    cfg = make_config("dqn", "env_1", "smoke", stall_truncate=25)
    assert cfg.stall_truncate == 25
    env = make_env(cfg)
    try:
        assert env.unwrapped.scenario.termination.stall_truncate == 25
    finally:
        env.close()
    off = make_env(make_config("dqn", "env_1", "smoke"))
    try:
        assert off.unwrapped.scenario.termination.stall_truncate == 0
    finally:
        off.close()
    data = cfg.to_dict()
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    assert load_run_config(tmp_path).stall_truncate == 25
    del data["stall_truncate"]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    assert load_run_config(tmp_path).stall_truncate == 0, "a run from before the option"
    with pytest.raises(TrainError, match="--stall-truncate"):
        make_config("dqn", "env_1", "smoke", stall_truncate=-3)
