"""One source for the test's episode length: each scenario's ``horizon``. `cosim test`, the
benchmark's test presets and ProtocolPlan default to None (the scenario's own), the env the
test drives then runs the scenario's horizon, and the report records the steps that ran."""

import dataclasses

import pytest

from cosim.scenario import load_scenario
from eval.cli import build_parser
from eval.cli.learn import _test_command
from eval.reporting import report
from eval.reporting.page import first_screen
from eval.reporting.report import provenance, task_version
from eval.scale.benchmark import TEST_SETTINGS
from eval.testing.conditions import TestConditions
from eval.testing.protocol import ProtocolPlan


def test_the_test_defaults_to_the_scenarios_horizon():
    args = build_parser().parse_args(["test", "--agents", "2", "--policy", "autopilot"])
    assert args.steps is None and ProtocolPlan().steps is None
    assert "--steps" not in _test_command(args)
    given = _test_command(_with(args, steps=77))
    assert given[given.index("--steps") + 1] == "77"
    # the benchmark's tests: smoke's 60-step check, the others the scenario's horizon
    assert {name: s.steps for name, s in TEST_SETTINGS.items()} == {
        "smoke": 60, "quick": None, "standard": None, "paper": None}


def _with(args, **changes):
    copy = type(args)(**vars(args))
    for key, value in changes.items():
        setattr(copy, key, value)
    return copy


def test_the_env_a_test_drives_runs_the_scenarios_horizon():
    sc = dataclasses.replace(load_scenario("env_1"), horizon=37)
    assert TestConditions.of(1, None).scenario(sc).horizon == 37
    assert TestConditions.of(2, 12).scenario(sc).horizon == 12
    env = TestConditions.of(2, None).env(sc, "continuous", 1, seed=0)
    try:
        assert env.scenario.horizon == 37
    finally:
        env.close()


def test_the_report_records_the_steps_that_ran():
    task = task_version(["env_1", "env_2"])
    horizon = load_scenario("env_1").horizon
    assert report.test_steps(None, task) == horizon == load_scenario("env_2").horizon
    assert report.test_steps(120, task) == 120
    assert report.test_steps(None, {"a": {"horizon": 600}, "b": {"horizon": 300}}) == {"a": 600, "b": 300}
    prov = provenance(policy="autopilot", plan=ProtocolPlan(envs=("env_1",), episodes=1), algos=["ppo"])
    assert prov["plan"]["steps"] == horizon
    text = "".join(first_screen(prov, ["ppo"], {"ppo": "PPO"}))
    dt = load_scenario("env_1").dt
    assert f"1 episode(s) of {horizon} steps ({horizon * dt:g} s)" in text


@pytest.mark.parametrize("steps", [0, -3])
def test_a_non_positive_test_length_is_refused_by_name(steps, capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["test", "--agents", "2", "--steps", str(steps)])
    assert "--steps" in capsys.readouterr().err
