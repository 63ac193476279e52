"""What the command line says (issue 28): every option's help and default, `cosim test`'s
checkpoint-per-slot table and its cross-environment refusal, and the benchmark's console
(one line per trial, no Ray snapshot warnings, no pybullet banner)."""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from gymnasium import spaces

from eval.cli import build_parser, main
from eval.scale.raysession import ray_available


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def _actions(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The commands that take options: each command, and for one with actions of its own
    (`cosim encoder train`) each of those instead, by their words after `cosim`."""
    out = {}
    for name, command in _subparsers(parser).items():
        nested = any(isinstance(a, argparse._SubParsersAction) for a in command._actions)
        out.update({f"{name} {n}": c for n, c in _subparsers(command).items()} if nested else {name: command})
    return out


def test_every_option_has_help_and_shows_its_default():
    parser = build_parser()
    assert "benchmark for multi-agent deep reinforcement learning" in parser.format_help()
    assert "the top layer" not in parser.format_help()  # the description, not an internal note
    commands = _actions(parser)
    assert {"scenarios", "drive", "view", "nets", "train", "test", "benchmark", "replay",
            "check-scenarios", "encoder train"} <= set(commands)
    missing = []
    for name, command in [("cosim", parser), *commands.items()]:
        formatter = command._get_formatter()
        for action in command._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            label = f"{name} {'/'.join(action.option_strings) or action.dest}"
            if not (action.help or "").strip():
                missing.append(f"{label}: no help")
            elif action.nargs != 0 and (action.option_strings or action.nargs in ("?", "*")) \
                    and "default" not in formatter._get_help_string(action):
                missing.append(f"{label}: default not shown")
    assert not missing, missing
    # the defaults as a user would type them, in the rendered help
    bench = commands["benchmark"].format_help()
    assert "(default: standard)" in bench and "(default: env_1 env_2 env_3 env_4 env_5)" in bench
    assert re.search(r"runs\s+the\s+`standard`\s+preset", bench) and re.search(r"30\s+trials", bench)
    # measured times live in docs/benchmarks.md, not in --help (they change with the machine)
    assert not re.search(r"\d\s*(min|h)\b|minute|hour", bench) and "docs/benchmarks.md" in bench
    test = commands["test"].format_help()
    assert "--allow-cross-env" in test and re.search(r"\(default:\s+the\s+scenario's\s+horizon", test) and "(default: runs)" in test


def test_help_of_every_command_prints(capsys):
    for name in [*_subparsers(build_parser()), *_actions(build_parser())]:
        with pytest.raises(SystemExit) as done:
            main([*name.split(), "--help"])
        assert done.value.code == 0
        assert "(default: " in capsys.readouterr().out or name in ("scenarios", "encoder")  # encoder: its actions


# -- cosim test: which checkpoint drives which slot, and where it was trained ------------
_AGENTS: dict[str, Path] = {}


def _run(root: Path, env: str, algo: str, acs=("ac_0", "ac_1")) -> Path:
    """A run folder as `cosim train` names it, with an untrained checkpoint per AC."""
    from agents.registry import CONTINUOUS, get_agent_class

    if algo not in _AGENTS:  # one agent per algorithm, copied (making one takes a second)
        _AGENTS[algo] = root.parent / f"{algo}.pt"
        action = spaces.Box(-1, 1, (2,), np.float32) if algo in CONTINUOUS else spaces.Discrete(9)
        get_agent_class(algo).from_spaces(spaces.Box(0, 255, (84, 84, 3), np.uint8), action).save(_AGENTS[algo])
    run = root / f"{env}__{algo}__0__20260101-000000"
    for ac in acs:
        (run / "checkpoints" / ac).mkdir(parents=True)
        shutil.copy(_AGENTS[algo], run / "checkpoints" / ac / "best.pt")
    (run / "state.json").write_text(json.dumps({"best": {ac: float(i) for i, ac in enumerate(acs)}}))
    return run


TEST = ["test", "--agents", "1", "--episodes", "1", "--steps", "3", "--references", "none",
        "--no-replays", "--quiet"]


def test_cross_environment_test_is_refused_then_warned_naming_checkpoint_and_both_envs(tmp_path, capsys):
    runs = tmp_path / "runs"
    _run(runs, "env_1", "ppo")
    ckpt = runs / "env_1__ppo__0__20260101-000000" / "checkpoints" / "ac_1" / "best.pt"
    out = tmp_path / "out"
    args = [*TEST, "--runs", str(runs), "--envs", "env_3", "--scenario", "2", "--out", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert str(ckpt) in err and "trained in env_1" in err and "env_3" in err
    assert "--allow-cross-env" in err and err.count("\n") == 1
    assert not out.exists()  # refused before anything ran

    assert main([*args, "--allow-cross-env"]) == 0
    captured = capsys.readouterr()
    assert "warning" in captured.err and str(ckpt) in captured.err
    assert "trained in env_1" in captured.err and "env_3" in captured.err
    # the console table: tested in, algorithm, trained in (flagged), the AC per slot
    table = captured.out.split("checkpoints per environment and slot")[1].splitlines()[1:3]
    assert table[0].split()[:4] == ["tested", "in", "algorithm", "trained"]
    assert table[1].split()[:4] == ["env_3", "ppo", "env_1", "(!)"]
    (folder,) = out.iterdir()
    slots = pd.read_csv(folder / "slots.csv")
    assert slots[["env", "algorithm", "slot", "trained_env", "cross_env"]].values.tolist() == [
        ["env_3", "ppo", "ac_0", "env_1", True]]
    prov = json.loads((folder / "provenance.json").read_text())
    assert prov["slots"][0]["checkpoint"].endswith("ac_0/best.pt")  # Scenario 2 drives ac_0
    assert "Checkpoints per environment and slot" in (folder / "index.md").read_text()


def test_each_environment_is_tested_with_its_own_runs_and_the_table_names_every_slot(tmp_path, capsys):
    runs = tmp_path / "runs"
    _run(runs, "env_1", "ppo", acs=("ac_0",))
    _run(runs, "env_3", "ppo", acs=("ac_0", "ac_1", "ac_2"))
    _run(runs, "env_1", "dqn", acs=("ac_0", "ac_1"))
    from eval.testing.checkpoints import find_checkpoints
    from eval.testing.protocol import ProtocolPlan
    from eval.testing.slots import slot_summary, slot_table

    per_env = {env: find_checkpoints(runs, ["ppo"], env=env) for env in ("env_1", "env_3")}
    assert [c["ppo"].parts[-4] for c in per_env.values()] == ["env_1__ppo__0__20260101-000000",
                                                       "env_3__ppo__0__20260101-000000"]
    per_env = {env: {**ckpts, "dqn": find_checkpoints(runs, ["dqn"], env="env_1")["dqn"]}
               for env, ckpts in per_env.items()}
    plan = ProtocolPlan(envs=("env_1", "env_3"), agents=2)
    table = slot_table(per_env, plan, ["ppo", "dqn"])
    assert len(table) == 2 * 2 * 2  # environments x algorithms x slots
    env1_ppo = table[(table.env == "env_1") & (table.algorithm == "ppo")]
    assert env1_ppo["how"].tolist() == ["own slot", "chosen AC"]  # the run trained no ac_1
    assert table[table.env == "env_3"]["cross_env"].tolist() == [False, False, True, True]
    text = slot_summary(table).splitlines()
    assert len(text) == 1 + 4, text  # a row per environment and algorithm here
    assert [line.split()[:5] for line in text[1:]] == [
        ["env_1", "ppo", "env_1", "ac_0", "ac_0*"], ["env_1", "dqn", "env_1", "ac_0", "ac_1"],
        ["env_3", "ppo", "env_3", "ac_0", "ac_1"], ["env_3", "dqn", "env_1", "(!)", "ac_0"]]
    # environments with the same checkpoints share a row
    shared = slot_table({e: per_env["env_3"] for e in ("env_2", "env_3")}, plan, ["ppo", "dqn"])
    assert [line.split()[:3] for line in slot_summary(shared).splitlines()[1:]] == [
        ["env_2", "ppo", "env_3"], ["env_2", "env_3", "dqn"], ["env_3", "ppo", "env_3"]]


# -- the benchmark's console ------------------------------------------------------------
def _cosim(args, tmp: Path, timeout: float = 600):
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "RAY_TMPDIR": str(tmp)}
    return subprocess.run([sys.executable, "-m", "eval.cli", *args], env=env, capture_output=True,
                          text=True, timeout=timeout)


def _console_checks(text: str, trials: int) -> None:
    lines = [line for line in text.splitlines() if line.strip()]
    progress = [line for line in lines if re.match(rf"\[\d+/{trials}\] trained ", line)]
    assert len(progress) == trials, text
    assert "pybullet build time" not in text and "snapshotting" not in text, text
    return lines


def test_benchmark_console_without_ray_is_a_line_per_trial(tmp_path):
    done = _cosim(["benchmark", "--preset", "smoke", "--envs", "env_1", "--algos", "ppo", "dqn",
                   "--steps", "40", "--no-ray", "--train-only", "--out", str(tmp_path / "b")], tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = _console_checks(done.stdout + done.stderr, 2)
    # the plan, a line per trial, the total, and once (not per trial) that the validation
    # env's SUMO runs in a child process (cosim/sumo_process.py, not TraCI: issue 57 item 14)
    assert len(lines) == 1 + 2 + 1 + 1, lines
    assert sum("runs in a child process" in line for line in lines) == 1 and "Retrying" not in done.stdout


@pytest.mark.slow  # ~2 min: Ray's start, three trials, the test and the report
@pytest.mark.skipif(not ray_available(), reason="Ray Tune is not installed (pip install -e '.[tune]')")
def test_benchmark_console_on_ray_is_short_with_a_line_per_trial(tmp_path):
    tmp = Path(__import__("tempfile").mkdtemp(prefix="cr", dir="/tmp"))  # Ray's socket paths are short
    try:
        done = _cosim(["benchmark", "--preset", "smoke", "--envs", "env_1", "--algos", "ppo", "dqn", "td3",
                       "--steps", "80", "--out", str(tmp_path / "b")], tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = _console_checks(done.stdout + done.stderr, 3)
    # the plan, 3 trials, the total, the test of env_1, the report's start, where it is
    assert len(lines) == 1 + 3 + 1 + 2 + 1, lines
    phases = [re.match(r"\[(\d+)/(\d+)\] (tested|the report)", line) for line in lines]
    counts = [(int(m[1]), int(m[2])) for m in phases if m]
    assert counts == [(1, 2), (2, 2)], lines  # the report's counter ends at its total
