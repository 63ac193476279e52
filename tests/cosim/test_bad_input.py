"""Every input a user can get wrong ends in one line that names it and the fix.

The CLI cases run `eval.cli.main` in this process with the file descriptors
captured (SUMO's own C++ messages included): the exit is 2, the last line
of stderr names the offending input, and no traceback is printed. API cases (an
environment's actions and reset options) raise a CosimError naming the input.
Scenario-validation cases (issue 10 item 3) are here too: each names the file and
the key.
"""

import subprocess
import sys
import time
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import yaml

from agents.a3c import A3C
from agents.td3 import TD3
from cosim.errors import ActionError, CosimError, OptionError, ScenarioError
from cosim.scenario import load_scenario, scenario_data, scenarios_dir
from eval.cli import main

OBS = gymnasium.spaces.Box(0, 255, (84, 84, 3), np.uint8)


def scenario_yaml(tmp_path: Path, name: str = "bad", base: str = "env_1", **changes) -> Path:
    """A copy of a bundled scenario with `changes`, its file paths made absolute."""
    data = scenario_data(base)
    data.pop("name", None)
    data.update(changes)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run_cli(argv: list[str], capfd) -> tuple[int, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own errors
        code = exc.code
    return code, capfd.readouterr().err


def _lots_yaml(tmp_path: Path) -> Path:
    demand = (scenarios_dir() / "../demand/env_3.rou.xml").resolve()
    text = demand.read_text()
    bad = tmp_path / "lots.rou.xml"
    bad.write_text(text.replace('probability="', 'probability="lots" x="', 1))
    return scenario_yaml(tmp_path, "lots", base="env_3", demand=[str(bad)])


def _checkpoint(tmp_path: Path, algo: str) -> Path:
    cls, space = {"a3c": (A3C, gymnasium.spaces.Discrete(9)),
                  "td3": (TD3, gymnasium.spaces.Box(-1, 1, (2,), np.float32))}[algo]
    path = tmp_path / f"{algo}.pt"
    cls.from_spaces(OBS, space, seed=0).save(path)
    return path


def _run_folder(tmp_path: Path, config_text: str) -> Path:
    run = tmp_path / "env_1__ppo__0__20260101-000000"
    run.mkdir()
    (run / "config.yaml").write_text(config_text)
    return run


def _acs(route, depart_pos=15) -> list[dict]:
    return [{"route": route, "depart_pos": depart_pos, "arrival_pos": -15, "lane": 0}]


# (id, argv builder (tmp_path -> argv), substrings the last stderr line must hold)
CASES = [
    ("view-steps-0", lambda t: ["view", "env_1", "--steps", "0"], ["--steps", "must be >= 1, got 0"]),
    ("view-image-size-0", lambda t: ["view", "--image-size", "0"], ["--image-size", "8..512, got 0"]),
    ("test-episodes-0", lambda t: ["test", "--policy", "random", "--episodes", "0"],
     ["--episodes", "got 0"]),
    ("test-steps-negative", lambda t: ["test", "--steps", "-5"], ["--steps", "got -5"]),
    ("test-out-under-a-file", lambda t: ["test", "--policy", "random", "--envs", "env_1",
                                         "--episodes", "1", "--steps", "5", "--quiet",
                                         "--out", str(_file(t) / "reports")],
     ["--out", "a_file", "cannot write"]),
    ("nets-check-missing-config", lambda t: ["nets", "check", "--config", "missing.netccfg"],
     ["missing.netccfg", "does not exist"]),
    ("resume-corrupt-config", lambda t: ["train", "--resume", str(_run_folder(t, "algo: [ppo\n"))],
     ["config.yaml", "malformed YAML"]),
    ("resume-unknown-config-key", lambda t: ["train", "--resume",
                                             str(_run_folder(t, "algo: ppo\nlearnin_rate: 3\n"))],
     ["config.yaml", "unknown key(s) ['learnin_rate']", "valid keys"]),
    ("checkpoint-starting-with-h", lambda t: ["test", "--agents", "1", "--envs", "env_1",
                                              "--checkpoint", f"ppo={_h_file(t)}"],
     ["h.pt", "truncated or corrupt"]),
    ("region-center-not-a-number", lambda t: ["drive", str(scenario_yaml(
        t, region={"center": ["zero", 0], "size": [290.0, 90.0]}))],
     ["bad.yaml", "'region'", "'center'", "'zero' is not a number"]),
    ("drive-steps-negative", lambda t: ["drive", "--steps", "-5"], ["--steps", "got -5"]),
    # issue 57 item 11: a seed numpy, torch or SUMO cannot take, refused by argparse
    ("drive-seed-negative", lambda t: ["drive", "--seed", "-1"], ["--seed", "0..2147483647, got -1"]),
    ("view-seed-negative", lambda t: ["view", "--seed", "-1"], ["--seed", "0..2147483647, got -1"]),
    ("test-seed-negative", lambda t: ["test", "--seed", "-1"], ["--seed", "0..2147483647, got -1"]),
    ("train-seed-negative", lambda t: ["train", "--seed", "-1", "--out", str(t / "runs")],
     ["--seed", "0..2147483647, got -1"]),
    ("train-seed-huge", lambda t: ["train", "--seed", "99999999999999999999999", "--out", str(t / "runs")],
     ["--seed", "0..2147483647, got 99999999999999999999999"]),
    ("benchmark-first-seed-huge", lambda t: ["benchmark", "--first-seed", "2147483648"],
     ["--first-seed", "0..2147483647, got 2147483648"]),
    ("drive-agents-7", lambda t: ["drive", "--agents", "7"], ["--agents", "1..6, got 7"]),
    ("demand-probability-lots", lambda t: ["drive", str(_lots_yaml(t)), "--steps", "1", "--quiet"],
     ["scenario 'lots'", "probability", "lots"]),
    ("gui-without-display", lambda t: ["drive", "env_1", "--gui", "--steps", "1"],
     ["--gui", "DISPLAY", "WAYLAND_DISPLAY"]),
    # scenario validation at load (item 3): the file and the key named
    ("route-a-string", lambda t: ["drive", str(scenario_yaml(t, acs=_acs("st_e")))],
     ["bad.yaml", "acs[0]", "'route' must be a list", "[st_e]"]),
    ("overlapping-spawns", lambda t: ["drive", str(scenario_yaml(t, acs=_acs(["st_e"]) * 2))],
     ["bad.yaml", "acs[0] and acs[1]", "0.0 m apart", "depart_pos"]),
    ("spawn-outside-region", lambda t: ["drive", str(scenario_yaml(
        t, acs=_acs(["st_e"]), region={"center": [-125.0, 150.0], "size": [100.0, 90.0]}))],
     ["bad.yaml", "acs[0].depart_pos", "outside the region"]),
    ("goal-outside-region", lambda t: ["drive", str(scenario_yaml(
        t, acs=_acs(["st_e"]), region={"center": [-200.0, 150.0], "size": [150.0, 90.0]}))],
     ["bad.yaml", "acs[0].arrival_pos", "outside the region"]),
    ("a3c-checkpoint-in-ppo-slot", lambda t: ["test", "--agents", "1", "--envs", "env_1",
                                              "--checkpoint", f"ppo={_checkpoint(t, 'a3c')}"],
     ["a3c.pt", "holds a a3c agent", "ppo AC"]),
    ("td3-checkpoint-in-discrete-slot", lambda t: ["test", "--agents", "1", "--envs", "env_1",
                                                   "--checkpoint", f"ppo={_checkpoint(t, 'td3')}"],
     ["td3.pt", "holds a td3 agent", "ppo AC"]),
]


def _file(tmp_path: Path) -> Path:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    return blocker


def _h_file(tmp_path: Path) -> Path:
    path = tmp_path / "h.pt"
    path.write_text("hello, not a checkpoint")
    return path


@pytest.mark.parametrize("make_argv, expected", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_cli_input_is_one_line_naming_it(make_argv, expected, tmp_path, capfd, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.chdir(tmp_path)
    argv = make_argv(tmp_path)
    started = time.monotonic()
    code, err = run_cli(argv, capfd)
    assert code == 2, f"exit {code}: every user error exits 2 (docs/reference.md#exit-codes-and-errors)"
    assert "Traceback" not in err and "unexpected error" not in err, err
    last = err.strip().splitlines()[-1]
    for text in expected:
        assert text in last, f"{text!r} not in the last line: {last!r}"
    assert time.monotonic() - started < 60, "refused before doing the work"


def test_out_under_a_file_fails_before_the_protocol_runs(tmp_path, capfd, monkeypatch):
    import eval.testing.session

    ran = []
    monkeypatch.setattr(eval.testing.session, "run_test", lambda *a, **k: ran.append(1))
    code, err = run_cli(["test", "--policy", "random", "--envs", "env_1", "--quiet",
                         "--out", str(_file(tmp_path) / "reports")], capfd)
    assert code != 0 and not ran and "--out" in err


def _not_utf8(tmp_path: Path) -> Path:
    path = scenario_yaml(tmp_path, "latin1")
    path.write_bytes(b"description: caf\xe9\n" + path.read_bytes())  # Latin-1, not UTF-8
    return path


def _folder_yaml(tmp_path: Path) -> Path:
    path = tmp_path / "x.yaml"
    path.mkdir()
    return path


# issue 57 item 10: each was a bare UnicodeDecodeError, IsADirectoryError or TypeError (title:
# a list, unhashable in roadmap's cache); now a ScenarioError naming the file, exit 2, no run folder
@pytest.mark.parametrize("make, says", [
    (_not_utf8, ["latin1.yaml", "not UTF-8", "save the file as UTF-8"]),
    (_folder_yaml, ["x.yaml", "is a folder", "scenario .yaml file"]),
    (lambda t: scenario_yaml(t, title=[1, 2]), ["bad.yaml", "'title' must be text", "[1, 2]"]),
], ids=["not-utf8", "a-folder", "title-a-list"])
def test_an_unreadable_or_mistyped_scenario_file_is_a_scenario_error_naming_it(make, says, tmp_path,
                                                                               capfd):
    path = make(tmp_path)
    with pytest.raises(ScenarioError) as raised:
        from cosim.roadmap import road_map

        road_map(load_scenario(path))
    assert all(text in str(raised.value) for text in says), raised.value
    code, err = run_cli(["train", "--env", str(path), "--steps", "10", "--out", str(tmp_path / "runs")],
                        capfd)
    assert code == 2 and err.count("\n") == 1 and "unexpected error" not in err, err
    assert all(text in err for text in says), err
    assert not (tmp_path / "runs").exists(), "no run folder for a refused scenario"


def test_drive_and_view_default_to_the_scenarios_ac_count(tmp_path, capfd):
    two = scenario_yaml(tmp_path, "two", acs=[
        {"route": ["st_e"], "depart_pos": 15, "arrival_pos": -15, "lane": 0},
        {"route": ["st_w"], "depart_pos": 15, "arrival_pos": -15, "lane": 0},
    ])
    assert load_scenario(two).max_agents == 2
    code, _ = run_cli(["drive", str(two), "--steps", "3", "--quiet"], capfd)
    assert code == 0
    code, err = run_cli(["view", str(two), "--steps", "2", "--moments", "1", "--quiet",
                         "--out", str(tmp_path / "view")], capfd)
    assert code == 0, err
    assert len(list((tmp_path / "view").glob("mosaic_*.png"))) == 1


@pytest.fixture(scope="module")
def mixed_env():
    from cosim.env import CosimParallelEnv

    env = CosimParallelEnv("env_1", num_agents=2, action_types=["discrete", "continuous"],
                           background=False)
    env.reset(seed=0)
    yield env
    env.close()


@pytest.mark.parametrize("action", [["fast", "left"], {"throttle": 1.0, "steer": 0.0}, "ab", None],
                         ids=["strings", "dict", "string", "none"])
def test_box_action_of_the_wrong_kind_names_the_agent_and_its_space(mixed_env, action):
    with pytest.raises(ActionError) as info:
        mixed_env.step({"ac_0": 0, "ac_1": action})
    text = str(info.value)
    assert "'ac_1'" in text and "Box(-1" in text and "\n" not in text


@pytest.mark.parametrize("seed", [-1, 1.5, "7", True])
def test_a_seed_that_is_not_a_whole_number_from_0_is_refused_naming_seed(mixed_env, seed):
    """issue 57 item 11: reset(seed=-1) and reset(seed=1.5) were numpy's errors, naming no seed."""
    import cosim

    with pytest.raises(OptionError, match=r"reset\(seed=\.\.\.\): the seed must be a whole number >= 0"):
        mixed_env.reset(seed=seed)
    with pytest.raises(OptionError, match=r"parallel_env\(seed=\.\.\.\)"):
        cosim.parallel_env("env_1", num_agents=1, seed=seed)
    single = cosim.single_env("env_1", background=False, pedestrians=False)
    with pytest.raises(OptionError, match=r"reset\(seed=\.\.\.\)"):  # before Gymnasium's own error
        single.reset(seed=seed)
    single.close()
    assert set(mixed_env.reset(seed=np.int64(3))[0]) == {"ac_0", "ac_1"}  # a numpy integer is fine


@pytest.mark.parametrize("seed", [-1, 2**64, 1.5])
def test_an_agent_seed_torch_or_numpy_cannot_take_names_seed(seed):
    with pytest.raises(ValueError, match=r"A3C\(seed=\.\.\.\): the seed must be a whole number 0..2\*\*64-1"):
        A3C.from_spaces(OBS, gymnasium.spaces.Discrete(9), seed=seed)


def test_reset_option_typo_is_refused_naming_the_valid_keys(mixed_env, caplog):
    with pytest.raises(OptionError, match=r"unknown option 'backgrund', did you mean 'background'\? "
                                          r"valid keys: \['background', 'pedestrians'\]"):
        mixed_env.reset(seed=1, options={"backgrund": False})
    with pytest.raises(OptionError, match="must be a dict"):
        mixed_env.reset(seed=1, options=["background"])
    # a key like no valid one (PettingZoo's API test sends {"options": 1}) is ignored, with a warning
    mixed_env.reset(seed=1, options={"options": 1})
    assert "ignoring unknown option 'options'" in caplog.text
    obs, _ = mixed_env.reset(seed=1, options={"background": False})  # the valid key still works
    assert set(obs) == {"ac_0", "ac_1"}


def test_every_deliberate_error_has_its_package_root():
    """cosim's errors (and eval's, above it) share cosim.errors.CosimError; agents, which never
    imports cosim, has its own root, agents.errors.AgentError; the CLI catches both."""
    from agents.checkpoint import CheckpointError
    from agents.errors import AgentError
    from agents.workers import WorkerError
    from eval.testing.protocol import ProtocolError
    from eval.training.presets import PresetError
    from eval.training.train import TrainError

    for cls in (ScenarioError, ActionError, OptionError, TrainError, ProtocolError, PresetError):
        assert issubclass(cls, CosimError) and not issubclass(cls, AgentError), cls
    for cls in (CheckpointError, WorkerError):
        assert issubclass(cls, AgentError) and not issubclass(cls, CosimError), cls


def _bad_presets(tmp_path, monkeypatch, edit) -> None:
    """eval/training/hyperparams/ copied to ``tmp_path``, changed by ``edit(folder)``, and read from there."""
    import eval.training.presets as presets

    for path in presets.HYPERPARAMS.glob("*.yaml"):
        (tmp_path / path.name).write_text(path.read_text())
    edit(tmp_path)
    load = presets.load_presets
    monkeypatch.setattr(presets, "load_presets", lambda folder=tmp_path: load(folder))


@pytest.mark.parametrize("command", [["train", "--algo", "ppo"], ["benchmark", "--no-ray"]])
def test_a_bad_preset_yaml_is_one_line_naming_the_file_for_the_commands_that_read_it(
        command, tmp_path, capfd, monkeypatch):
    """train and benchmark read eval/training/hyperparams/*.yaml: a typo there is one line naming the
    file and the fix (exit 2), never a traceback."""
    _bad_presets(tmp_path, monkeypatch,
                 lambda folder: (folder / "td3.yaml").write_text("quick: {steps: 10\n"))  # unclosed
    code, err = run_cli(command, capfd)
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("cosim: error: ") and "td3.yaml: not valid YAML at line 2" in err, err
    assert "fix that file" in err and "docs/reference.md#presets" in err


@pytest.mark.parametrize("command", [["scenarios"], ["train", "--help"], ["test", "--help"]])
def test_a_bad_preset_yaml_leaves_the_commands_that_do_not_read_it_working(command, tmp_path, capfd,
                                                                           monkeypatch):
    _bad_presets(tmp_path, monkeypatch,
                 lambda folder: (folder / "td3.yaml").write_text("quick: {steps: 10\n"))
    code, err = run_cli(command, capfd)
    assert code == 0 and err == "", err


def test_a_preset_yaml_with_an_unknown_key_names_the_key_and_the_valid_ones(tmp_path, capfd,
                                                                           monkeypatch):
    def misspell(folder):
        runs = yaml.safe_load((folder / "runs.yaml").read_text())
        runs["quick"]["horizn"] = 10
        (folder / "runs.yaml").write_text(yaml.safe_dump(runs))

    _bad_presets(tmp_path, monkeypatch, misspell)
    code, err = run_cli(["train", "--algo", "dqn"], capfd)
    assert code == 2 and err.count("\n") == 1, err
    assert "runs.yaml: quick: unknown key(s) ['horizn']; valid keys: " in err and "'horizon'" in err


def test_a_bug_prints_one_line_and_the_log_holding_its_traceback(capfd, monkeypatch):
    import eval.cli.sim

    def broken(args):
        raise RuntimeError("something deep inside\nwith a second line")

    monkeypatch.setattr(eval.cli.sim, "cmd_scenarios", broken)
    code, err = run_cli(["scenarios"], capfd)
    assert code == 1 and err.count("\n") == 1 and "Traceback" not in err
    assert "unexpected error RuntimeError: something deep inside" in err
    log = Path(err.split("traceback in ")[1].split(";")[0])
    assert "Traceback" in log.read_text() and "broken" in log.read_text()
    log.unlink()


def test_a_multi_line_error_prints_its_first_line_and_keeps_the_rest_in_a_log(capfd, monkeypatch):
    import eval.cli.sim
    from agents.workers import WorkerError

    def worker_died(args):
        raise WorkerError(1, "exited with code 1", "Traceback (most recent call last):\n  boom")

    monkeypatch.setattr(eval.cli.sim, "cmd_scenarios", worker_died)
    code, err = run_cli(["scenarios"], capfd)
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err  # a user error (AgentError)
    assert err.startswith("cosim: error: worker 1 failed: exited with code 1 (details in ")
    log = Path(err.split("details in ")[1].rstrip(")\n"))
    assert "boom" in log.read_text()
    log.unlink()


def test_a_closed_pipe_ends_the_command_quietly():
    # `cosim benchmark --status | head`: the reader went away; no "unexpected error", no log
    code = ("import sys, eval.cli, eval.cli.sim\n"
            "def gone(args):\n"
            "    print('a line', flush=True)\n"
            "    raise BrokenPipeError(32, 'Broken pipe')\n"
            "eval.cli.sim.cmd_scenarios = gone\n"
            "sys.exit(eval.cli.main(['scenarios']))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 141 and done.stderr == "", done.stderr
