"""The test's conditions are built in one place (issue 26): eval/testing/conditions.py.

Every environment the test drives (its two scenarios, replays, cross-play and sweeps), the
validity suite's scenarios, training's validation episodes and `cosim view` come from one
:class:`TestConditions` call each, and nothing else sets the test's rules (a collision
does not end an episode). Checked by reading the code with ``ast``."""

import ast
import dataclasses
from pathlib import Path

import eval
from cosim.scenario import load_scenario
from eval.testing.conditions import TestConditions, action_kinds

ROOT = Path(eval.__file__).resolve().parents[1]
SOURCES = sorted([*(ROOT / "eval").rglob("*.py"), *(ROOT / "studies").glob("*.py")])
HOME = ROOT / "eval" / "testing" / "conditions.py"
USES = {
    "eval/testing/jobs.py": 1,  # run_job: a Scenario 1 slot order or an AC alone
    "eval/testing/replay.py": 1,  # either scenario, as the report's records were taken
    "eval/testing/robustness.py": 2,  # cross-play, sweeps
    "eval/testing/validity.py": 1,  # the degenerate-policy suite (and the references)
    "eval/training/validation.py": 1,  # held-out validation episodes
    "eval/training/encoder.py": 1,  # the perception encoder's frames (`cosim encoder train`)
    "eval/cli/sim.py": 1,  # cosim view
    "studies/train_env1.py": 1,
    "studies/greedy_vs_sampled.py": 1,
}
"""Where TestConditions is constructed, and how many times: one call site per use."""


def _calls(path: Path):
    return [n for n in ast.walk(ast.parse(path.read_text(), str(path))) if isinstance(n, ast.Call)]


def _name(func: ast.expr) -> str:
    if isinstance(func, ast.Name):
        return func.id
    if isinstance(func, ast.Attribute):
        return f"{_name(func.value)}.{func.attr}"
    return ""


def test_the_test_conditions_are_constructed_once_per_use():
    found = {}
    for path in SOURCES:
        if path == HOME:
            continue
        n = sum(_name(c.func) in ("TestConditions", "TestConditions.of") for c in _calls(path))
        if n:
            found[path.relative_to(ROOT).as_posix()] = n
    assert found == USES


def test_no_other_place_builds_a_test_environments_rules():
    wrong = []
    for path in SOURCES:
        if path == HOME:
            continue
        where = path.relative_to(ROOT).as_posix()
        for call in _calls(path):
            for kw in call.keywords:  # a collision that does not end the episode: the test's rule
                if kw.arg in ("terminate_on_collision", "on_collision") and \
                        isinstance(kw.value, ast.Constant) and kw.value.value is False:
                    wrong.append(f"{where}:{call.lineno} {kw.arg}=False")
            # eval builds environments through TestConditions; training's own (its rules are
            # the run's --collisions) is the one other
            if where.startswith("eval/") and _name(call.func).endswith("CosimParallelEnv") and \
                    where != "eval/training/trainer.py":
                wrong.append(f"{where}:{call.lineno} CosimParallelEnv(...)")
    assert not wrong, "build the test's environment with eval.testing.conditions.TestConditions:\n" + \
        "\n".join(wrong)


def test_the_conditions_of_each_scenario():
    assert action_kinds(["ppo", "td3", "dqn", "autopilot"]) == ["discrete", "continuous", "discrete", "continuous"]
    assert TestConditions.of(1, 40) == TestConditions(steps=40)
    assert TestConditions.of(2, 40) == TestConditions(steps=40, background=False, pedestrians=False)
    env = TestConditions.of(2, 7).env("env_1", action_kinds(["td3"]))
    try:
        assert env.possible_agents == ["ac_0"] and env.action_types == {"ac_0": "continuous"}
        assert env.scenario.horizon == 7 and env.scenario.termination.on_collision is False
        assert (env._background, env._pedestrians) == (False, False)
    finally:
        env.close()
    sc = load_scenario("env_3")
    sc = sc.with_overrides(termination=dataclasses.replace(sc.termination, on_collision=True))
    under = TestConditions().scenario(sc)
    assert under.termination.on_collision is False and under.horizon == sc.horizon
    assert TestConditions(steps=9).scenario(sc).horizon == 9
