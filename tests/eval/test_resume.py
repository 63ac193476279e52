"""Interrupted training runs resume exactly: kills at chosen moments, then `--resume`.

Each case trains a real smoke-preset run in a subprocess (tests/eval/_interrupt.py
sends the signal at an exact moment of a checkpoint), resumes it, interrupts it
again, and so on, then resumes it to the end. After every interruption the run
must resume: CSV rows covered by the last committed checkpoint are kept as they
were, later ones are redone once (no gap, no duplicate, one header), the step
counters continue from the checkpoint, and no partial file is left behind.
"""

import csv
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import agents
from eval.cli import main
from eval.training.train import RunLock, TrainError, train

INTERRUPT = [sys.executable, str(Path(__file__).with_name("_interrupt.py"))]
COSIM = [sys.executable, "-m", "eval.cli"]
STEPS = 160  # smoke preset: a checkpoint every 40 steps, episodes of at most 60 steps


def _rows(run: Path) -> list[dict]:
    path = run / "episodes.csv"
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _state(run: Path) -> dict | None:
    path = run / "state.json"
    return json.loads(path.read_text()) if path.exists() else None


def _snapshot(run: Path) -> dict:
    return {"state": _state(run), "rows": _rows(run)}


def _train_cmd(run_root: Path, algo: str, steps: int = STEPS) -> list[str]:
    return ["train", "--algo", algo, "--preset", "smoke", "--steps", str(steps),
            "--out", str(run_root), "--quiet"]


def _interrupted(args: list[str], moment: str, nth: int, sig: str) -> None:
    proc = subprocess.run(INTERRUPT + [moment, str(nth), sig, "--"] + args,
                          capture_output=True, text=True, timeout=300)
    expected = -signal.SIGKILL if sig == "KILL" else 130
    assert proc.returncode == expected, proc.stderr[-3000:]
    if sig == "INT":
        assert proc.stderr.strip().splitlines()[-1] == "cosim: interrupted"


def _check_consistent(run: Path, snapshots: list[dict], steps: int = STEPS) -> None:
    """The invariants of a finished run that was interrupted at `snapshots`."""
    final = _state(run)
    assert final["env_steps"] == steps, "the step counter reached the budget"
    rows = _rows(run)
    assert all(r["agent"] != "agent" for r in rows), "one header, never a header read as a row"
    for ac in ("ac_0", "ac_1"):
        episodes = [int(r["episode"]) for r in rows if r["agent"] == ac]
        assert episodes == list(range(len(episodes))), f"{ac}: episodes continue, no gap, no repeat"
        assert final["episodes"][ac] == len(episodes)
        steps = [int(r["env_step"]) for r in rows if r["agent"] == ac]
        assert steps == sorted(steps)
    for snap in snapshots:
        state = snap["state"]
        if state is None:
            continue
        kept = state["csv_rows"]
        assert rows[:kept] == snap["rows"][:kept], "rows the checkpoint covered are kept as they were"
        later = [int(r["env_step"]) for r in rows[kept:]]
        assert all(s > state["env_steps"] for s in later[: len(snap["rows"]) - kept])
    leftovers = [p.name for p in (run / "checkpoints").rglob("*") if p.is_file()
                 and p.name not in ("latest.pt", "best.pt")]
    assert leftovers == [], "no pending or temporary checkpoint file is left"
    assert (run / "run.lock").read_text() == "", "the lock was released"


def _run_chain(tmp_path: Path, algo: str, kills: list[tuple[str, int, str]], steps: int = STEPS) -> None:
    """Train, interrupt at each of `kills` (resuming in between), then resume to the end."""
    _interrupted(_train_cmd(tmp_path, algo, steps), *kills[0])
    (run,) = tmp_path.iterdir()
    snapshots = [_snapshot(run)]
    committed = []
    for kill in kills[1:]:
        _interrupted(["train", "--resume", str(run), "--quiet"], *kill)
        snap = _snapshot(run)
        if snapshots[-1]["state"] is not None:  # counters never go back
            assert snap["state"]["env_steps"] >= snapshots[-1]["state"]["env_steps"]
        snapshots.append(snap)
        if snap["state"] is not None:
            committed.append(snap["state"]["env_steps"])
    if kills[0][1] == 1 and kills[0][0] != "committed":
        assert snapshots[0]["state"] is None, "the first kill came before any checkpoint"
    train(None, resume=run, progress=False)
    _check_consistent(run, snapshots, steps)
    if committed:  # the agents' own counters continued from the committed checkpoint
        final_agent = agents.load(run / "checkpoints" / "ac_0" / "latest.pt")
        assert getattr(final_agent, "steps", 1) > 0


def test_kills_before_during_and_after_checkpoints_then_resume(tmp_path):
    """SIGKILL halfway through writing a file of the first checkpoint (before any is
    committed), then SIGINT after the first checkpoint (rows written since are redone)."""
    _run_chain(tmp_path, "ppo", [("saving", 1, "KILL"), ("enter", 2, "INT")], steps=120)


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["ppo", "td3", "a3c"])
@pytest.mark.parametrize("kills", [
    [("enter", 1, "INT"), ("pending", 1, "KILL"), ("enter", 3, "INT")],
    [("saving", 1, "INT"), ("committed", 1, "KILL"), ("pending", 2, "INT")],
    [("pending", 2, "KILL"), ("saving", 1, "KILL"), ("committed", 1, "INT")],
], ids=["enter-pending-enter", "saving-committed-pending", "pending-saving-committed"])
def test_every_moment_and_signal_then_resume(tmp_path, algo, kills):
    _run_chain(tmp_path, algo, kills)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kills_at_random_times_then_resume(tmp_path, seed):
    """SIGKILL or SIGINT from outside at random wall-clock moments, three times, then resume."""
    rng = random.Random(seed)
    run = None
    snapshots = []
    for _ in range(3):
        args = _train_cmd(tmp_path, "ppo") if run is None else ["train", "--resume", str(run), "--quiet"]
        proc = subprocess.Popen(COSIM + args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(4.0, 14.0))
        proc.send_signal(rng.choice([signal.SIGKILL, signal.SIGINT]))
        proc.wait(timeout=120)
        run = run or next(tmp_path.iterdir())
        snapshots.append(_snapshot(run))
        if proc.returncode == 0:  # finished before the signal: nothing left to interrupt
            break
    train(None, resume=run, progress=False)
    _check_consistent(run, snapshots)


def _hold_lock(run: Path) -> subprocess.Popen:
    code = ("import sys, time; from pathlib import Path; from eval.training.train import RunLock; "
            "RunLock(Path(sys.argv[1])); print('locked', flush=True); time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", code, str(run)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    return holder


def test_second_concurrent_resume_is_refused_naming_the_pid(tmp_path, capsys):
    run = _run_folder_with_config(tmp_path)
    holder = _hold_lock(run)
    try:
        assert main(["train", "--resume", str(run), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"in use by process PID {holder.pid}" in err
        assert not (run / "episodes.csv").exists(), "the refused process touched nothing"
        with pytest.raises(TrainError, match=f"PID {holder.pid}"):
            RunLock(run)
    finally:
        holder.kill()
        holder.wait()
    # the holder died without releasing: its lock is taken over, the PID replaced
    assert (run / "run.lock").read_text().strip() == str(holder.pid)
    lock = RunLock(run)
    assert (run / "run.lock").read_text().strip() == str(os.getpid())
    lock.release()


def test_recover_checkpoints_rolls_the_committed_step_forward_and_drops_the_rest(tmp_path):
    from eval.training.train import recover_checkpoints

    folder = tmp_path / "checkpoints" / "ac_0"
    folder.mkdir(parents=True)
    for name, text in [("latest.pt", "old"), ("latest.pending-80.pt", "new"), ("best.pending-80.pt", "b"),
                       ("latest.pending-120.pt", "uncommitted"), ("latest.pending-120.pt.tmp", "half")]:
        (folder / name).write_text(text)
    recover_checkpoints(tmp_path, committed_step=80)
    assert sorted(p.name for p in folder.iterdir()) == ["best.pt", "latest.pt"]
    assert (folder / "latest.pt").read_text() == "new" and (folder / "best.pt").read_text() == "b"
    recover_checkpoints(tmp_path, committed_step=None)  # no checkpoint committed: the run restarts
    assert list(folder.iterdir()) == []


def test_unreadable_state_json_is_named(tmp_path, capsys):
    run = _run_folder_with_config(tmp_path)
    (run / "state.json").write_text('{"env_steps": ')
    assert main(["train", "--resume", str(run), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "state.json is unreadable" in err
    assert (run / "run.lock").read_text() == "", "the lock was released"


def _run_folder_with_config(tmp_path: Path) -> Path:
    run = tmp_path / "env_1__ppo__0__20260101-000000"
    run.mkdir()
    (run / "config.yaml").write_text("algo: ppo\nenv: env_1\nagents: 2\nsteps: 40\npreset: smoke\n")
    return run


def test_resume_with_more_steps_trains_a_run_further(tmp_path, capsys):
    """`cosim train --resume RUN --steps N` raises the budget (config.yaml keeps it) and trains
    on from the run's latest.pt; a lower budget, and a finished run that kept only best.pt,
    are refused in one line."""
    import yaml

    from eval.training.runfolder import read_state
    from eval.training.train import make_config

    cfg = make_config("ppo", "env_1", "smoke", agents=1, steps=40)
    run = train(cfg, tmp_path / "runs", quiet=True, progress=False, keep="all")
    assert read_state(run)["env_steps"] == 40
    assert main(["train", "--resume", str(run), "--steps", "130", "--quiet"]) == 0
    assert read_state(run)["env_steps"] == 130
    assert yaml.safe_load((run / "config.yaml").read_text())["steps"] == 130
    episodes = list(csv.DictReader((run / "episodes.csv").open()))
    assert [int(e["env_step"]) for e in episodes] == [100]  # the 60-step episode after the extension
    capsys.readouterr()
    assert main(["train", "--resume", str(run), "--steps", "60", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--steps 60 is below the 130" in err
    pruned = train(cfg, tmp_path / "pruned", quiet=True, progress=False, keep="best")
    with pytest.raises(TrainError, match=r"kept only best.pt for ac_0.*--keep all"):
        train(None, resume=pruned, steps=80, quiet=True, progress=False)
    assert (pruned / "run.lock").read_text() == "", "the lock was released"
