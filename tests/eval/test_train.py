"""`cosim train`: smoke runs of the six algorithms, kill -9 and resume, bad input."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import agents
from eval.cli import main
from eval.training.train import ALGORITHMS, TrainError, make_config, train

COSIM = [sys.executable, "-m", "eval.cli"]


def _rows(run: Path) -> list[dict]:
    with open(run / "episodes.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow  # six algorithms trained end to end (~50 s); the children's options: test_run_options.py
@pytest.mark.timeout(1000)  # the run's own budget is 900 s (under 2 min on a quiet machine)
def test_train_all_smoke_gives_a_loadable_checkpoint_per_algorithm(tmp_path):
    proc = subprocess.run(
        COSIM + ["train", "--algo", "all", "--preset", "smoke", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=900,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    # one progress bar over the six runs' steps (their --quiet lines move it), a line per run
    assert "train all" in proc.stderr and f"{120 * 6}/{120 * 6}" in proc.stderr, proc.stderr[-2000:]
    assert all(f"{algo}: done, run folder " in proc.stdout for algo in ALGORITHMS), proc.stdout
    assert "pybullet build time" not in proc.stdout + proc.stderr
    runs = {p.name.split("__")[1]: p for p in tmp_path.iterdir()}
    assert sorted(runs) == sorted(ALGORITHMS)
    obs = np.zeros((84, 84, 12), np.uint8)  # the presets' 4-frame stack
    for algo, run in runs.items():
        for ac in ("ac_0", "ac_1"):  # --keep best (the default): the finished run keeps the policy
            assert sorted(p.name for p in (run / "checkpoints" / ac).iterdir()) == ["best.pt"]
            agent = agents.load(run / "checkpoints" / ac / "best.pt")
            assert agent.algo == algo and agent.policy_only
            stored = torch.load(run / "checkpoints" / ac / "best.pt", weights_only=True)["state"]["networks"]
            dtypes = {t["dtype"] for net in stored.values() for t in net.values()}
            assert dtypes == {"<f2"}, dtypes  # the smoke preset's policy_dtype: float16 on disk
            assert all(p.dtype == torch.float32 for net in agent.networks.values() for p in net.parameters())
            action = agent.act(obs, deterministic=True)
            assert agent.action_space.contains(
                np.asarray(action, dtype=agent.action_space.dtype) if algo in ("ddpg", "td3") else int(action)
            )
            with pytest.raises(ValueError, match=r"trained on 4 stacked camera frame\(s\) \(84x84x12\) but is "
                               r"given 1 \(84x84x3\); use --frame-stack 4") as info:
                agent.act(obs[..., :3], deterministic=True)
            assert "\n" not in str(info.value)
        assert json.loads((run / "selection.json").read_text())["basis"] == "validation"
        state = json.loads((run / "state.json").read_text())
        assert state["env_steps"] == 120
        assert (run / "convergence.png").exists() and (run / "manifest.json").exists()
        assert list((run / "tb").iterdir()), "TensorBoard scalars were written"


def test_keep_all_keeps_the_resumable_checkpoint_and_prune_drops_only_covered_ones(tmp_path):
    from eval.training.runfolder import prune_finished

    cfg = make_config("dqn", "env_1", "smoke", steps=40)
    run = train(cfg, tmp_path, quiet=True, progress=False, keep="all")
    folders = sorted((run / "checkpoints").iterdir())
    assert [sorted(p.name for p in f.iterdir()) for f in folders] == [["best.pt", "latest.pt"]] * 2
    full = agents.load(folders[0] / "latest.pt", require_full=True)
    policy = agents.load(folders[0] / "best.pt")
    assert not full.policy_only and policy.policy_only
    with pytest.raises(agents.CheckpointError, match="policy only"):
        agents.load(folders[0] / "best.pt", require_full=True)
    (folders[1] / "best.pt").unlink()  # an AC without best.pt keeps its latest.pt
    size = (folders[0] / "latest.pt").stat().st_size
    assert prune_finished(run, "best") == size
    assert [sorted(p.name for p in f.iterdir()) for f in folders] == [["best.pt"], ["latest.pt"]]
    with pytest.raises(ValueError, match="keep policy"):
        prune_finished(run, "none")


def _wait_for_checkpoint(run_root: Path, proc, at_least: int, timeout: float = 300) -> Path:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for state in run_root.glob("*/state.json"):
            try:
                if json.loads(state.read_text())["env_steps"] >= at_least:
                    return state.parent
            except (json.JSONDecodeError, KeyError):
                pass  # being replaced right now: read again
        if proc.poll() is not None:
            raise AssertionError(f"training ended early: {proc.returncode}")
        proc_wait = min(0.2, deadline - time.monotonic())
        try:
            proc.wait(timeout=max(proc_wait, 0.01))
        except subprocess.TimeoutExpired:
            pass
    raise AssertionError("no checkpoint appeared in time")


def test_kill_9_then_resume_continues_without_gaps_or_duplicates(tmp_path):
    proc = subprocess.Popen(
        COSIM + ["train", "--algo", "ppo", "--preset", "smoke", "--steps", "600", "--out", str(tmp_path), "--quiet"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        run = _wait_for_checkpoint(tmp_path, proc, at_least=80)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    at_kill = json.loads((run / "state.json").read_text())
    rows_at_kill = _rows(run)
    assert len(rows_at_kill) >= at_kill["csv_rows"]
    assert at_kill["env_steps"] < 600

    train(None, resume=run, progress=False)

    final = json.loads((run / "state.json").read_text())
    assert final["env_steps"] == 600
    rows = _rows(run)
    for ac in ("ac_0", "ac_1"):
        episodes = [int(r["episode"]) for r in rows if r["agent"] == ac]
        assert episodes == list(range(len(episodes))), "episode numbers continue, no gap, no repeat"
        steps = [int(r["env_step"]) for r in rows if r["agent"] == ac]
        assert steps == sorted(steps)
    # the rows the checkpoint covered are kept as they were; later ones were redone, not doubled
    assert rows[: at_kill["csv_rows"]] == rows_at_kill[: at_kill["csv_rows"]]
    assert all(int(r["env_step"]) > at_kill["env_steps"] for r in rows[at_kill["csv_rows"]:])
    # what was lost: at most one checkpoint interval (40 steps) of progress
    progress_at_kill = max([int(r["env_step"]) for r in rows_at_kill] + [at_kill["env_steps"]])
    assert progress_at_kill - at_kill["env_steps"] <= 40 + 60  # + an episode still being written


def test_unknown_algorithm_and_environment_name_the_choices(capsys):
    assert main(["train", "--algo", "sac"]) == 2
    err = capsys.readouterr().err
    assert "unknown algorithm 'sac'" in err and "ppo, a3c, impala, dqn, ddpg, td3" in err
    assert main(["train", "--algo", "ppo", "--env", "env_42"]) == 2
    assert "available: env_1, env_2, env_3, env_4, env_5" in capsys.readouterr().err


def test_action_type_mismatch_is_refused_with_the_reason():
    with pytest.raises(TrainError, match="dqn cannot train with continuous actions.*Discrete"):
        make_config("dqn", action_type="continuous")
    with pytest.raises(TrainError, match="td3 cannot train with discrete actions.*continuous values"):
        make_config("td3", action_type="discrete")


def test_unwritable_output_fails_before_training(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    started = time.monotonic()
    assert main(["train", "--algo", "ppo", "--preset", "smoke", "--out", str(blocker / "runs")]) == 2
    assert "cannot write to output folder" in capsys.readouterr().err
    assert time.monotonic() - started < 20


def test_hyperparameter_overrides_are_typed_and_checked(capsys):
    cfg = make_config("td3", hyper={"actor_learning_rate": "1e-4", "buffer_size": "5000", "hidden": "[64, 64]"})
    assert cfg.agent_config.actor_learning_rate == 1e-4
    assert cfg.agent_config.buffer_size == 5000 and cfg.agent_config.hidden == (64, 64)
    assert cfg.agent_config.reward_scale == 0.01  # the preset's, untouched
    with pytest.raises(TrainError, match="td3 has no such hyperparameter; valid: .*actor_learning_rate"):
        make_config("td3", hyper={"learning_rate": "1e-4"})
    with pytest.raises(TrainError, match=r"buffer_size=lots: expected an int like 20000"):
        make_config("td3", hyper={"buffer_size": "lots"})
    with pytest.raises(TrainError, match="tau=0.0 is out of range"):
        make_config("td3", hyper={"tau": "0"})
    assert main(["train", "--algo", "ppo", "--set", "learning_rate"]) == 2
    assert "write FIELD=VALUE" in capsys.readouterr().err
