"""studies/pilot_task.py (issue 25's pilot runs): its tables and its resume logic on fabricated
runs and records, and its smoke version end to end (old and new arms), rerun."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from cosim.dynamics import DISCRETE_ACTIONS, discrete_controls
from cosim.scenario import load_scenario
from eval.training.config import TrainConfig

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "studies" / "pilot_task.py"


@pytest.fixture(scope="module")
def pilot(load_study):
    return load_study("pilot_task")


def _args(pilot, out: Path, *extra: str):
    return pilot.parse(["--out", str(out), *extra])


# -- the plan and the resume logic ---------------------------------------------------------------
def _fake_run(out: Path, arm: str, env: str, algo: str, steps_done: int | None, total=100) -> Path:
    stem = env + ("_old" if arm == "old" else "")
    run = out / "runs" / arm / f"{stem}__{algo}__0__20261125-000000"
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.yaml").write_text(yaml.safe_dump(TrainConfig(algo=algo, env=env, steps=total).to_dict()))
    if steps_done is not None:
        (run / "state.json").write_text(json.dumps({"env_steps": steps_done, "csv_rows": 0}))
    return run


def test_reruns_skip_finished_runs_resume_unfinished_ones_and_skip_finished_tests(pilot, tmp_path):
    args = _args(pilot, tmp_path, "--arms", "old", "new", "--envs", "env_4")
    C = pilot.Cell
    unfinished = _fake_run(tmp_path, "new", "env_4", "ppo", 40)
    _fake_run(tmp_path, "new", "env_4", "dqn", 100)
    _fake_run(tmp_path, "old", "env_4", "ppo", None)         # killed before its first checkpoint
    _fake_run(tmp_path, "old", "env_4", "dqn", 100)
    (tmp_path / "test").mkdir()
    (tmp_path / "test" / "old__env_4__dqn.parquet").write_bytes(b"")  # tested
    assert pilot.run_status(pilot.find_run(tmp_path, C("new", "env_4", "ppo"), 0)) == "unfinished"
    assert pilot.run_status(pilot.find_run(tmp_path, C("new", "env_4", "dqn"), 0)) == "finished"
    assert pilot.run_status(pilot.find_run(tmp_path, C("new", "env_3", "dqn"), 0)) == "missing"
    to_train, to_test = pilot.plan_work(tmp_path, args)
    assert [c.name for c in to_train] == ["old__env_4__ppo", "new__env_4__ppo"]
    assert [c.name for c in to_test] == ["new__env_4__dqn"]
    # an unfinished run resumes; a missing one starts with its arm's flags and the same budget
    cmd = pilot.train_command(tmp_path, C("new", "env_4", "ppo"), args, unfinished)
    assert cmd[-3:] == ["--resume", str(unfinished), "--quiet"]
    old = pilot.train_command(tmp_path, C("old", "env_3", "dqn"), _args(pilot, tmp_path, "--steps", "500"), None)
    new = pilot.train_command(tmp_path, C("new", "env_3", "dqn"), _args(pilot, tmp_path, "--steps", "500"), None)
    assert old[old.index("--env") + 1] == str(tmp_path / "scenarios" / "env_3_old.yaml")
    assert old[-6:] == ["--collisions", "end", "--frame-stack", "1", "--validation-episodes", "0"]
    assert new[new.index("--env") + 1] == "env_3" and new[-2:] == ["--steps", "500"]
    assert old[old.index("--steps") + 1] == "500" and old[old.index("--preset") + 1] == "quick"
    nav = pilot.train_command(tmp_path, C("nav", "env_3", "dqn"), args, None)
    assert nav[-2:] == ["--obs", "nav"]
    # a finished run of a shorter budget, in a plan with more steps, trains on to the plan's
    longer = _args(pilot, tmp_path, "--arms", "new", "--envs", "env_4", "--steps", "300")
    assert pilot.run_status(pilot.find_run(tmp_path, C("new", "env_4", "dqn"), 0), 300) == "unfinished"
    done = pilot.find_run(tmp_path, C("new", "env_4", "dqn"), 0)
    assert pilot.train_command(tmp_path, C("new", "env_4", "dqn"), longer, done)[-5:] == [
        "--resume", str(done), "--quiet", "--steps", "300"]
    assert pilot.train_command(tmp_path, C("new", "env_4", "ppo"), args, unfinished)[-1] == "--quiet"
    # --keep all: the run keeps each AC's last checkpoint, new or resumed (cosim train --keep)
    keep = _args(pilot, tmp_path, "--keep", "all")
    fresh = pilot.train_command(tmp_path, C("new", "env_4", "ppo"), keep, None)
    resumed = pilot.train_command(tmp_path, C("new", "env_4", "ppo"), keep, unfinished)
    assert fresh[fresh.index("--keep") + 1] == "all" and resumed[resumed.index("--keep") + 1] == "all"
    assert "--keep" not in pilot.train_command(tmp_path, C("new", "env_4", "ppo"), args, None)


def test_the_curriculum_arm_pretrains_on_straight_first_then_warm_starts_each_cell(pilot, tmp_path):
    """The curriculum arm: one pretrain run per algorithm on env_1 first, with --pretrain-steps;
    its cells wait for it, then start from it with the rest of the budget."""
    args = _args(pilot, tmp_path, "--arms", "curriculum", "--algos", "ppo", "--steps", "150",
                 "--pretrain-steps", "40")
    to_train, to_test = pilot.plan_work(tmp_path, args)
    assert [c.name for c in to_train] == ["pretrain__env_1__ppo", "curriculum__env_3__ppo",
                                          "curriculum__env_4__ppo"] and to_test == []
    pre = pilot.train_command(tmp_path, to_train[0], args, None)
    assert pre[pre.index("--env") + 1] == "env_1" and pre[pre.index("--steps") + 1] == "40"
    assert pre[-5:] == ["--obs", "nav", "--share-params", "--set", "action_repeat=2"]
    assert not pilot.startable(tmp_path, to_train[1], args)
    with pytest.raises(pilot.PilotError, match="starts from pretrain__env_1__ppo, which has no run"):
        pilot.train_command(tmp_path, to_train[1], args, None)
    source = _fake_run(tmp_path, "pretrain", "env_1", "ppo", 20, total=40)
    assert not pilot.startable(tmp_path, to_train[1], args)  # unfinished
    (source / "state.json").write_text(json.dumps({"env_steps": 40, "csv_rows": 0}))
    assert pilot.startable(tmp_path, to_train[1], args)
    cmd = pilot.train_command(tmp_path, to_train[1], args, None)
    assert cmd[cmd.index("--steps") + 1] == "110" and cmd[cmd.index("--init-from") + 1] == str(source)
    assert [c.name for c in pilot.plan_work(tmp_path, args)[0]] == ["curriculum__env_3__ppo",
                                                                    "curriculum__env_4__ppo"]
    with pytest.raises(SystemExit):
        _args(pilot, tmp_path, "--arms", "curriculum", "--steps", "150", "--pretrain-steps", "150")
    warm = _args(pilot, tmp_path, "--arms", "warm", "--algos", "ppo", "--init-from", "clone.pt")
    cmd = pilot.train_command(tmp_path, pilot.Cell("warm", "env_3", "ppo"), warm, None)
    assert cmd[cmd.index("--init-from") + 1] == str(Path("clone.pt").resolve())
    for alone in (["--arms", "warm"], ["--arms", "new", "--init-from", "clone.pt"]):
        with pytest.raises(SystemExit):
            _args(pilot, tmp_path, *alone)


def test_the_camera_arms_train_on_the_route_and_on_their_own_frozen_encoder(pilot, tmp_path, capsys):
    image, route = tmp_path / "image.pt", tmp_path / "route.pt"
    image.write_bytes(b"x")
    route.write_bytes(b"y")
    args = _args(pilot, tmp_path, "--arms", "new", "route", "encoder", "encoder-route", "--algos", "dqn",
                 "--encoder", str(image), "--route-encoder", str(route))
    cmds = {arm: pilot.train_command(tmp_path, pilot.Cell(arm, "env_2", "dqn"), args, None)
            for arm in args.arms}
    assert "--obs" not in cmds["new"] and "--encoder" not in cmds["new"]
    assert cmds["route"][cmds["route"].index("--obs") + 1] == "route" and "--encoder" not in cmds["route"]
    assert cmds["encoder"][cmds["encoder"].index("--encoder") + 1] == str(image) and "--obs" not in cmds["encoder"]
    both = cmds["encoder-route"]
    assert both[both.index("--encoder") + 1] == str(route) and both[both.index("--obs") + 1] == "route"
    for wrong in (["--arms", "encoder"], ["--arms", "new", "--encoder", str(image)],
                  ["--arms", "encoder", "--encoder", str(tmp_path / "missing.pt")]):
        with pytest.raises(SystemExit):
            _args(pilot, tmp_path, *wrong)
    assert "no such file; build one with `cosim encoder train`" in capsys.readouterr().err
    pilot.check_plan(tmp_path, args)
    with pytest.raises(pilot.PilotError, match="started with"):  # another encoder is another plan
        pilot.check_plan(tmp_path, _args(pilot, tmp_path, "--arms", "encoder", "--encoder", str(route)))


def test_a_rerun_with_another_plan_is_refused_and_nav_needs_the_obs_flag(pilot, tmp_path):
    pilot.check_plan(tmp_path, _args(pilot, tmp_path, "--steps", "500"))
    pilot.check_plan(tmp_path, _args(pilot, tmp_path, "--steps", "500", "--arms", "new"))  # arms may change
    with pytest.raises(pilot.PilotError, match="started with --steps 500"):
        pilot.check_plan(tmp_path, _args(pilot, tmp_path, "--steps", "600"))
    with pytest.raises(pilot.PilotError, match="nav arm needs `cosim train --obs nav`"):
        pilot.check_obs_flag("usage: cosim train [--algo ALGO] [--frame-stack K]")
    pilot.check_obs_flag("usage: cosim train [--obs {image,nav}]")


def test_the_old_arms_scenario_is_the_environment_with_the_old_wheel(pilot, tmp_path):
    path = pilot.old_scenario(tmp_path, "env_3")
    old, new = load_scenario(path), load_scenario("env_3")
    assert old.vehicle.max_lateral_accel == math.inf
    assert np.array_equal(discrete_controls(old.vehicle), DISCRETE_ACTIONS)
    assert old.with_overrides(vehicle=new.vehicle, source=new.source) == new  # nothing else differs


# -- tables --------------------------------------------------------------------------------------
def _records(returns: dict[str, list[float]], goals: dict[str, list[bool]], contacts=0) -> pd.DataFrame:
    """Per-step test records: each (episode, slot) has two steps carrying its return."""
    rows = []
    for slot, rs in returns.items():
        for ep, r in enumerate(rs):
            for step in (1, 2):
                rows.append({"episode": ep, "agent": slot, "step": step, "reward": r / 2,
                             "goal_reached": goals[slot][ep] and step == 2,
                             "collision": step <= contacts, "checkpoint": f"x/{slot}/best.pt"})
    return pd.DataFrame(rows)


def test_tables_say_whether_a_run_clears_always_brake_and_a_turning_slot_reaches_goals(pilot, tmp_path):
    routes = pd.DataFrame({"slot": ["ac_0", "ac_1"], "movement": ["straight", "left"],
                           "turning": [False, True]})
    ppo = pilot.slot_table(pilot.per_slot(_records(
        {"ac_0": [100, 50], "ac_1": [-20, 10]}, {"ac_0": [True, True], "ac_1": [False, True]},
        contacts=1)), routes, env="env_3", arm="new", algo="ppo", car="new", row="new ppo")
    dqn = pilot.slot_table(pilot.per_slot(_records(
        {"ac_0": [10, 10], "ac_1": [10, 10]}, {"ac_0": [True, True], "ac_1": [False, False]})),
        routes, env="env_3", arm="new", algo="dqn", car="new", row="new dqn")
    brake_rows = pd.DataFrame({"episode": [0, 0, 1, 1], "slot": ["ac_0", "ac_1"] * 2,
                               "return": [20.0] * 4, "goal": [0.0] * 4, "contact_steps": [0.0] * 4})
    brake = pilot.slot_table(brake_rows, routes, env="env_3", arm="reference", algo="always-brake",
                             car="new", row="ref: always-brake")
    table = pd.concat([ppo, dqn, brake], ignore_index=True)
    by = table.set_index(["row", "slot"])
    assert by.loc[("new ppo", "ac_0"), "return"] == 75 and by.loc[("new ppo", "ac_1"), "goal"] == 0.5
    assert by.loc[("new ppo", "ac_1"), "contact_steps"] == 1.0
    assert by.loc[("new ppo", "ac_1"), "checkpoint"] == "x/ac_1/best.pt"
    md, met = pilot.env_summary(table, "env_3")
    lines = {line.split(" | ")[0][2:]: line for line in md.splitlines()[2:]}
    # ppo: mean return (100 + 50 - 20 + 10) / 4 = 35 > 20; goals 3/4; turning slot ac_1 0.5
    # then DS, RC of the turning slots, events (records without the driving score: -), every
    # turning slot >= 0.5 goals, DS above the safe non-turner's (none here: -)
    assert lines["new ppo"] == ("| new ppo | 35.0 | 0.75 | 0.50 | 1.00 | 0.50 | 1.0 | yes | yes (ac_1) "
                                "| - | - | - | yes | - |")
    assert lines["new dqn"] == "| new dqn | 10.0 | 0.50 | 0.00 | 1.00 | 0.00 | 0.0 | no | no | - | - | - | no | - |"
    assert lines["ref: always-brake"].endswith("| - | no | - | - | - | no | - |")
    assert "ac_1 left*" in md.splitlines()[0] and "ac_0 straight |" in md.splitlines()[0]
    assert met == ["new ppo"]
    args = _args(pilot, tmp_path, "--envs", "env_3", "--arms", "new")
    assert "- `new` arm: **met** by ppo" in pilot.summary(table, args)
    args = _args(pilot, tmp_path, "--envs", "env_3", "env_4", "--arms", "new")
    text = pilot.summary(table, args)
    assert "**not met** (met in {'new ppo': ['env_3']})" in text and "nothing tested yet" in text


def test_a_state_arm_meets_its_target_with_every_turning_slot_at_half_its_goals_and_ds_above_safe(pilot):
    """Issue 61's target for the state arms: every turning slot >= 0.5 goals on the test and the
    driving score above the safe non-turner's; the per-slot DS and RC come from the records."""
    routes = pd.DataFrame({"slot": ["ac_0", "ac_1"], "movement": ["straight", "left"],
                           "turning": [False, True]})

    def records(goal_1: list[bool], rc_1: float) -> pd.DataFrame:
        rec = _records({"ac_0": [100, 100], "ac_1": [50, 50]},
                       {"ac_0": [True, True], "ac_1": goal_1})
        return rec.assign(event_vehicle=False, event_pedestrian=False, event_object=False,
                          red_light=False, route_completion=np.where(rec["agent"] == "ac_1", rc_1, 0.5))

    good = pilot.slot_table(pilot.per_slot(records([True, False], 0.4)), routes, env="env_2",
                            arm="state", algo="dqn", car="new", row="state dqn")
    bad = pilot.slot_table(pilot.per_slot(records([False, False], 0.4)), routes, env="env_2",
                           arm="state-step", algo="dqn", car="new", row="state-step dqn")
    safe = pilot.slot_table(pd.DataFrame({"episode": [0, 0], "slot": ["ac_0", "ac_1"], "return": [1.0, 1.0],
                                          "goal": [1.0, 0.0], "contact_steps": [0.0, 0.0],
                                          "DS": [1.0, 0.1], "RC": [1.0, 0.1], "events": [0.0, 0.0]}),
                            routes, env="env_2", arm="reference", algo="safe-non-turner", car="new",
                            row="ref: safe-non-turner")
    table = pd.concat([good, bad, safe], ignore_index=True)
    by = table.set_index(["row", "slot"])
    # ac_1: goal in one episode (RC 1), RC 0.4 in the other: DS 0.7; ac_0 reaches both goals: 1.0
    assert by.loc[("state dqn", "ac_1"), "DS"] == pytest.approx(0.7)
    md, met = pilot.env_summary(table, "env_2")
    assert met == ["state dqn"]  # 0.85 > 0.55 and its turner at 0.5; state-step's turner at 0
    lines = {line.split(" | ")[0][2:]: line for line in md.splitlines()[2:]}
    assert lines["state dqn"].endswith("| 0.85 | 0.70 | 0.00 | yes | yes |")
    assert lines["state-step dqn"].endswith("| no | yes |")


def test_slot_routes_read_the_turns_from_the_scenario(pilot):
    env3 = pilot.slot_routes("env_3").set_index("slot")
    assert not env3.loc["ac_2", "turning"] and env3.loc["ac_4", "movement"] == "left"
    env4 = pilot.slot_routes("env_4").set_index("slot")
    assert env4["turning"].all()  # every roundabout route turns on entering
    assert list(env4["movement"]) == ["left", "right", "straight", "straight", "right", "left"]


# -- end to end ----------------------------------------------------------------------------------
@pytest.mark.slow
def test_smoke_study_end_to_end_and_rerun(tmp_path):
    """Old and new arms, PPO and DQN on env_4 with 40 training steps, one 40-step test episode
    (~1 minute); the rerun trains and tests nothing."""
    cmd = [sys.executable, str(SCRIPT), "--smoke", "--arms", "old", "new", "--out", str(tmp_path)]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    table = pd.read_csv(tmp_path / "results.csv")
    trained = table[table["arm"] != "reference"]
    assert set(zip(trained["arm"], trained["algo"], strict=True)) == {
        ("old", "ppo"), ("old", "dqn"), ("new", "ppo"), ("new", "dqn")}
    assert len(trained) == 4 * 2 and set(trained["slot"]) == {"ac_0", "ac_1"}  # the smoke's 2 ACs
    assert set(trained[trained["arm"] == "old"]["car"]) == {"old"}
    refs = table[table["arm"] == "reference"]
    assert set(refs["row"]) == {"ref: always-brake", "ref: safe-non-turner", "ref: autopilot-discrete",
                                "ref: autopilot", "ref: autopilot-discrete (old wheel)"}
    cfg = yaml.safe_load(next((tmp_path / "runs" / "old").glob("env_4_old__ppo__0__*/config.yaml")).read_text())
    assert cfg["env"].endswith("env_4_old.yaml") and cfg["collisions_end_episode"] is True
    assert cfg["frame_stack"] == 1 and cfg["validation_episodes"] == 0 and cfg["steps"] == 40
    summary = (tmp_path / "summary.md").read_text()
    assert "| old ppo |" in summary and "\n## Target\n" in summary
    again = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and "0 to train, 0 to test" in again.stderr, again.stderr[-2000:]


def test_training_children_die_with_the_driver(pilot):
    """The `cosim train` children get the driver's pid in COSIM_OWNER_PID: they stop resumably
    when it dies (the mechanism: tests/eval/test_hardening.py, `--algo all`'s children)."""
    import os

    from eval.cli.learn import OWNER_ENV

    env = pilot._child_env()
    assert env[OWNER_ENV] == str(os.getpid())
    assert env["PYTHONPATH"].split(os.pathsep)[0] == str(ROOT)
