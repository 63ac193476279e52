"""`cosim train --envs 2` on the real simulator: a smoke run, and kill -9 then resume.

Slow (two simulators per run): run with ``python3 -m pytest -m slow tests/eval/test_train_vector.py``.
"""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

import agents
from agents.workers import live_pids
from eval.training.train import train

COSIM = [sys.executable, "-m", "eval.cli"]
pytestmark = pytest.mark.slow


def _rows(run: Path) -> list[dict]:
    with open(run / "episodes.csv", newline="") as f:
        return list(csv.DictReader(f))


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def test_ppo_smoke_with_two_env_processes_via_the_cli(tmp_path):
    proc = subprocess.run(COSIM + ["train", "--algo", "ppo", "--preset", "smoke", "--envs", "2",
                                   "--device", "cpu", "--out", str(tmp_path), "--quiet"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (run,) = tmp_path.iterdir()
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    assert cfg["envs"] == 2 and cfg["device"] == "cpu"
    state = json.loads((run / "state.json").read_text())
    assert state["env_steps"] == 120
    rows = _rows(run)
    assert rows and len(rows) == state["csv_rows"]
    for ac in ("ac_0", "ac_1"):
        assert [int(r["episode"]) for r in rows if r["agent"] == ac] == list(range(sum(r["agent"] == ac for r in rows)))
        agent = agents.load(run / "checkpoints" / ac / "best.pt", device="cpu")  # --keep best
        assert agent.algo == "ppo" and agent.steps > 0


def test_kill_9_with_two_env_processes_leaves_no_worker_and_resumes(tmp_path):
    proc = subprocess.Popen(
        COSIM + ["train", "--algo", "dqn", "--preset", "smoke", "--steps", "400", "--envs", "2",
                 "--out", str(tmp_path), "--quiet"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 400
        state_path = None
        while time.monotonic() < deadline:
            runs = list(tmp_path.iterdir())
            if runs and (runs[0] / "state.json").exists():
                state_path = runs[0] / "state.json"
                if json.loads(state_path.read_text())["env_steps"] >= 80:
                    break
            assert proc.poll() is None, f"training ended early: {proc.returncode}"
            time.sleep(0.2)
        assert state_path is not None, "no checkpoint appeared in time"
        workers = [p for p in _children(proc.pid) if p]
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    deadline = time.monotonic() + 10
    while live_pids(workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert len(workers) >= 2 and live_pids(workers) == []
    run = state_path.parent
    at_kill = json.loads(state_path.read_text())
    rows_at_kill = _rows(run)

    train(None, resume=run, progress=False)

    final = json.loads((run / "state.json").read_text())
    assert final["env_steps"] >= 400
    rows = _rows(run)
    assert rows[: at_kill["csv_rows"]] == rows_at_kill[: at_kill["csv_rows"]]
    for ac in ("ac_0", "ac_1"):
        episodes = [int(r["episode"]) for r in rows if r["agent"] == ac]
        assert episodes == list(range(len(episodes)))
    assert all(int(r["env_step"]) > at_kill["env_steps"] for r in rows[at_kill["csv_rows"]:])
