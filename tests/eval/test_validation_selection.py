"""best.pt and the AC that represents a run are chosen on validation episodes under the
test's rules, not by training return (eval/training/runlog.py, eval/training/validation.py; docs/task.md,
"Checkpoint selection")."""

from __future__ import annotations

import json

import pytest

from eval.training.config import make_config


class _Agent:
    """Stands in for a trained agent: save() writes which checkpoint it is."""

    def __init__(self):
        self.step = 0

    def save(self, path, policy_only: bool = False, policy_dtype: str = "float32") -> None:
        path.write_text(json.dumps({"step": self.step}))


def _runlog(tmp_path, monkeypatch, validation: dict[int, dict[str, float]], episodes=2, select_by="return",
            ds: dict[int, dict[str, float]] | None = None):
    """A RunLog whose validation returns ``validation[step]`` (returns) and ``ds[step]`` (driving
    scores, NaN when not given) at each checkpoint."""
    import eval.training.validation
    from eval.training.runlog import RunLog

    cfg = make_config("dqn", "env_1", "smoke", agents=2, validation_episodes=episodes, select_by=select_by)
    calls = []

    def both(self, agents):
        step = next(iter(agents.values())).step
        calls.append(step)
        scores = (ds or {}).get(step, dict.fromkeys(agents, float("nan")))
        return {"return": dict(validation[step]), "ds": dict(scores)}

    monkeypatch.setattr(eval.training.validation.Validator, "both", both)
    return RunLog(tmp_path, cfg, None), calls


def _checkpoints(log, agents, steps):
    try:
        for step in steps:
            for a in agents.values():
                a.step = step
            log.checkpoint(agents, step)
    finally:
        log.close()


def test_select_by_driving_score_picks_by_it_and_a_tie_goes_to_the_later_checkpoint(tmp_path, monkeypatch):
    from eval.training.validation import RULE, rule

    assert make_config("dqn", "env_1", "smoke").select_by == "return"  # the default
    assert RULE == rule("return") and "mean undiscounted return" in RULE
    returns = {40: {"ac_0": 900.0, "ac_1": 5.0}, 80: {"ac_0": 100.0, "ac_1": 7.0},
               120: {"ac_0": -50.0, "ac_1": 1.0}}
    # ac_0: the highest return at 40, the best driving score at 80; ac_1: DS ties at 80 and 120
    ds = {40: {"ac_0": 0.20, "ac_1": 0.0}, 80: {"ac_0": 0.60, "ac_1": 0.5}, 120: {"ac_0": 0.30, "ac_1": 0.5}}
    log, calls = _runlog(tmp_path, monkeypatch, returns, select_by="ds", ds=ds)
    agents = {"ac_0": _Agent(), "ac_1": _Agent()}
    _checkpoints(log, agents, (40, 80, 120))
    best = lambda ac: json.loads((tmp_path / "checkpoints" / ac / "best.pt").read_text())["step"]  # noqa: E731
    assert best("ac_0") == 80  # by return it would be 40
    assert best("ac_1") == 120  # 0.5 at 80 and at 120: the later
    record = json.loads((tmp_path / "selection.json").read_text())
    assert record["select_by"] == "ds" and record["rule"] == rule("ds") and "driving score" in record["rule"]
    assert record["best"]["ac_0"] == {"score": 0.6, "env_step": 80}
    assert record["representative"] == "ac_0"
    assert [h["ds"] for h in record["history"]] == [ds[40], ds[80], ds[120]]  # both kinds recorded
    assert [h["return"] for h in record["history"]] == [returns[40], returns[80], returns[120]]
    assert [h["scores"] for h in record["history"]] == [ds[40], ds[80], ds[120]]


def test_select_by_return_keeps_the_first_of_equal_returns(tmp_path, monkeypatch):
    returns = {40: {"ac_0": 10.0, "ac_1": 3.0}, 80: {"ac_0": 10.0, "ac_1": 4.0}}
    log, _ = _runlog(tmp_path, monkeypatch, returns, select_by="return")
    agents = {"ac_0": _Agent(), "ac_1": _Agent()}
    _checkpoints(log, agents, (40, 80))
    best = lambda ac: json.loads((tmp_path / "checkpoints" / ac / "best.pt").read_text())["step"]  # noqa: E731
    assert (best("ac_0"), best("ac_1")) == (40, 80)
    record = json.loads((tmp_path / "selection.json").read_text())
    assert record["select_by"] == "return" and "mean undiscounted return" in record["rule"]
    with pytest.raises(ValueError, match="--select-by"):
        make_config("dqn", "env_1", "smoke", select_by="goal")


def _episode(log, agent, ret, step):
    log.episode(agent, {"return": ret, "length": 10, "n_collision_vehicle": 0, "n_collision_pedestrian": 0,
                        "n_collision_object": 0, "n_lane_violation": 0, "DISTANCE": 0.0,
                        "mean_speed_kmh": 0.0}, step)


def test_best_checkpoint_and_representative_ac_follow_validation_not_training_return(tmp_path, monkeypatch):
    from eval.testing import selection

    # ac_0 trains better and better but validates worse; ac_1 trains worse but validates best
    validation = {40: {"ac_0": -100.0, "ac_1": -300.0}, 80: {"ac_0": -900.0, "ac_1": -50.0}}
    log, calls = _runlog(tmp_path, monkeypatch, validation, select_by="return")
    agents = {"ac_0": _Agent(), "ac_1": _Agent()}
    try:
        for step, (r0, r1) in ((40, (10.0, -500.0)), (80, (500.0, -600.0))):
            for a in agents.values():
                a.step = step
            for _ in range(3):
                _episode(log, "ac_0", r0, step)
                _episode(log, "ac_1", r1, step)
            log.checkpoint(agents, step)
    finally:
        log.close()
    assert calls == [40, 80]
    best = lambda ac: json.loads((tmp_path / "checkpoints" / ac / "best.pt").read_text())["step"]  # noqa: E731
    assert best("ac_0") == 40  # by training return it would be 80 (return 500 > 10)
    assert best("ac_1") == 80
    record = json.loads((tmp_path / "selection.json").read_text())
    assert record["basis"] == "validation" and "test's rules" in record["rule"]
    assert record["best"] == {"ac_0": {"score": -100.0, "env_step": 40}, "ac_1": {"score": -50.0, "env_step": 80}}
    assert record["representative"] == "ac_1"  # ac_0 has by far the higher training return
    assert [h["scores"] for h in record["history"]] == [validation[40], validation[80]]
    assert len(record["seeds"]) == 2 and min(record["seeds"]) >= 10**9  # held out from training and test
    chosen = selection.choose(tmp_path)
    assert (chosen.ac, chosen.basis) == ("ac_1", "state.json best (validation)")


def test_validation_off_keeps_the_training_return_rule(tmp_path, monkeypatch):
    log, calls = _runlog(tmp_path, monkeypatch, {}, episodes=0)
    agents = {"ac_0": _Agent(), "ac_1": _Agent()}
    try:
        for step, ret in ((40, 10.0), (80, 500.0)):
            for a in agents.values():
                a.step = step
            for _ in range(3):
                _episode(log, "ac_0", ret, step)
                _episode(log, "ac_1", ret - 1, step)
            log.checkpoint(agents, step)
    finally:
        log.close()
    assert calls == []
    assert json.loads((tmp_path / "checkpoints" / "ac_0" / "best.pt").read_text())["step"] == 80
    assert json.loads((tmp_path / "selection.json").read_text())["basis"] == "training return"


def test_validation_seeds_are_disjoint_from_training_and_test_seeds():
    from eval.training.validation import validation_seeds

    seeds = validation_seeds(make_config("ppo", "env_1", "smoke", seed=3, validation_episodes=4))
    assert len(set(seeds)) == 4 and all(10**9 <= s < 2**31 for s in seeds)
    assert make_config("ppo", "env_1", "quick").validation_episodes == 2
    assert make_config("ppo", "env_1", "smoke").validation_episodes == 1  # the preset's own
    with pytest.raises(ValueError, match="--validation-episodes must be >= 0"):
        make_config("ppo", "env_1", "smoke", validation_episodes=-1)


def test_validation_episodes_are_as_long_as_the_test_allows():
    """A slot whose goal takes the autopilot 300-530 steps (env_4 ac_5, env_3 ac_4) is judged on
    reaching it: validation runs the preset's horizon, at most the scenario's (the test's)."""
    from cosim.scenario import load_scenario

    test_steps = load_scenario("env_4").horizon
    assert test_steps == 600
    assert make_config("ppo", "env_4", "standard").validation_steps == test_steps
    assert make_config("ppo", "env_4", "paper").validation_steps == test_steps  # horizon 2000
    assert make_config("ppo", "env_4", "quick").validation_steps == 300  # quick's horizon
    assert make_config("ppo", "env_4", "standard", validation_steps=50).validation_steps == 50


def test_validation_drives_the_acs_under_the_test_rules(tmp_path):
    """A real validation: the run's two ACs drive 2 short held-out episodes of the stacked
    env (collisions go on) and each gets its mean undiscounted return."""
    import gymnasium as gym
    import numpy as np

    from eval.training.validation import Validator

    cfg = make_config("dqn", "env_1", "smoke", agents=2, validation_episodes=2, validation_steps=5)

    class Brake:
        algo = "dqn"
        space = gym.spaces.Discrete(9)

        def __init__(self):
            self.shapes = set()

        def act(self, obs, deterministic=True):
            self.shapes.add(obs.shape)
            return 4  # the paper's table: index 4 brakes

    validator = Validator(cfg)
    agents = {"ac_0": Brake(), "ac_1": Brake()}
    try:
        both = validator.both(agents)
        assert validator._env.unwrapped.scenario.termination.on_collision is False
    finally:
        validator.close()
    assert set(both["return"]) == {"ac_0", "ac_1"} and all(np.isfinite(v) for v in both["return"].values())
    # a car that brakes from its spawn point (where it starts rolling) drives ~1% of its route
    assert set(both["ds"]) == {"ac_0", "ac_1"} and all(0.0 <= v < 0.05 for v in both["ds"].values())
    assert agents["ac_0"].shapes == {(84, 84, 3 * cfg.frame_stack)}
