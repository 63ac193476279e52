"""`cosim benchmark` and `cosim train --pbt` on Ray Tune (eval/scale/benchmark.py, eval/scale/pbt.py).

Each Ray run is a `cosim` subprocess with its own RAY_TMPDIR, so the test can tell
its Ray processes (GCS, raylet, workers inherit the variable) from anyone else's
and end exactly those. Tests that need Ray skip when it is not installed.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml

from eval.scale.raysession import ray_available

needs_ray = pytest.mark.skipif(not ray_available(),
                               reason="Ray Tune is not installed (pip install -e '.[tune]')")
PBT_STEPS, PBT_INTERVAL = 180, 60


@pytest.fixture
def ray_tmp():
    """A short RAY_TMPDIR (Ray's socket paths must stay under 107 characters); on the way
    out, the test asserts that no process of this Ray is left, and ends any that is."""
    path = Path(tempfile.mkdtemp(prefix="cr", dir="/tmp"))
    yield path
    left = wait_gone(path)
    for pid in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    assert not left, f"Ray processes left behind: {left}"
    shutil.rmtree(path, ignore_errors=True)  # Ray's session logs


def wait_gone(tmp: Path, grace: float = 15.0) -> dict[int, str]:
    """The Ray processes of ``tmp`` still alive after ``grace`` seconds (PID -> command line):
    a worker whose raylet ended notices it within a few seconds on a loaded machine."""
    deadline = time.monotonic() + grace
    while ray_pids(tmp) and time.monotonic() < deadline:
        time.sleep(0.5)
    left = {}
    for pid in ray_pids(tmp):
        try:
            left[pid] = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:200]
        except OSError:
            continue
    return left


def ray_pids(tmp: Path) -> list[int]:
    """PIDs of live processes started with RAY_TMPDIR=tmp (Ray's processes inherit it)."""
    needle = f"RAY_TMPDIR={tmp}\0".encode()
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            if needle in (proc / "environ").read_bytes():
                status = (proc / "status").read_text()
                if "\nState:\tZ" not in status:
                    found.append(int(proc.name))
        except OSError:
            continue
    return found


def cosim(args: list[str], ray_tmp: Path | None = None, timeout: float = 600,
          env_extra: dict | None = None, **kwargs):
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env_extra or {})}
    if ray_tmp is not None:
        env["RAY_TMPDIR"] = str(ray_tmp)
    return subprocess.run([sys.executable, "-m", "eval.cli", *args], env=env, capture_output=True,
                          text=True, timeout=timeout, **kwargs)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def tensors(path: Path) -> dict:
    import torch

    def flat(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict):
                yield from flat(v, f"{prefix}{k}.")
            elif torch.is_tensor(v):
                yield f"{prefix}{k}", v
    return dict(flat(torch.load(path, map_location="cpu", weights_only=True)["state"]))


# -- without Ray ---------------------------------------------------------------------
def test_plan_agents_reach_every_trial_and_old_plans_still_match():
    from eval.scale.benchmark import BenchmarkError, BenchmarkPlan

    base = BenchmarkPlan(preset="quick", envs=("env_1", "env_3"), algos=("ppo", "td3"), seeds=2)
    three = BenchmarkPlan(preset="quick", envs=("env_1", "env_3"), algos=("ppo", "td3"), seeds=2,
                          agents=3)
    assert {c.agents for c in base.cells()} == {6}  # the quick preset's count
    assert {c.agents for c in three.cells()} == {3} and len(three.cells()) == 8
    # a benchmark.json written before --agents existed has no such key: --resume still matches
    assert "agents" not in base.to_dict() and three.to_dict() == {**base.to_dict(), "agents": 3}
    with pytest.raises(BenchmarkError, match="--agents must be >= 1"):
        BenchmarkPlan(agents=0)


def test_plan_collisions_reach_every_trial_and_the_default_is_the_saved_plan():
    from eval.scale.benchmark import BenchmarkError, BenchmarkPlan

    grid = {"preset": "quick", "envs": ("env_4",), "algos": ("dqn", "td3"), "seeds": 2}
    end, cont = BenchmarkPlan(**grid, collisions="end"), BenchmarkPlan(**grid)
    assert {c.collisions_end_episode for c in end.cells()} == {True}
    assert {c.collisions_end_episode for c in cont.cells()} == {False} and len(cont.cells()) == 4
    assert BenchmarkPlan(**grid, collisions="event") == cont  # the default, also when named
    assert cont.to_dict() == {**end.to_dict(), "collisions": "event"}
    assert {c.collision_charge for c in BenchmarkPlan(**grid, collisions="step").cells()} == {"step"}
    # a plan saved before the rule was recorded (no key) trained under "end", and reads so
    assert BenchmarkPlan(**grid, collisions=None) == end
    with pytest.raises(BenchmarkError, match="--collisions must be event or step or end"):
        BenchmarkPlan(collisions="stop")


def test_tune_starts_the_one_cpu_trials_first_so_two_share_two_cores():
    """standard: A3C and IMPALA step 2 environments (2 CPUs), the others 1; on 2 cores a
    2-CPU trial at the head of Tune's queue left one core idle beside a 1-CPU trial."""
    from eval.scale.benchmark import BenchmarkPlan, packed, trial_resources

    cells = BenchmarkPlan(preset="standard", envs=("env_1", "env_3"), seeds=1).cells()
    order = packed(cells, max_cpus=2)
    cpus = [trial_resources(c, 2)["cpu"] for c in order]
    assert sorted(cpus) == cpus and set(cpus) == {1, 2}, cpus
    assert sorted(map(id, order)) == sorted(map(id, cells)), "the same cells, reordered"
    ones = [(c.env, c.algo) for c in order if trial_resources(c, 2)["cpu"] == 1]
    assert ones == [(c.env, c.algo) for c in cells if trial_resources(c, 2)["cpu"] == 1], \
        "the grid's order holds within a group"
    assert [trial_resources(c, 1)["cpu"] for c in packed(cells, max_cpus=1)] == [1] * len(cells)


def _fake_training(monkeypatch) -> list[str]:
    """Patch the benchmark's trainer: each trial leaves a finished run folder at once (its
    config.yaml) and its cell name in the returned list, in training order."""
    from eval.scale import benchmark

    trained = []

    def fake_train_cell(cfg, folder, keep="all"):
        trained.append(benchmark.cell_name(cfg))
        run = Path(folder) / "run"
        run.mkdir(parents=True)
        (run / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict()))
        return run

    monkeypatch.setattr(benchmark, "train_cell", fake_train_cell)
    return trained


def test_resume_with_more_seeds_trains_only_the_new_seeds(tmp_path, monkeypatch):
    from eval.scale.benchmark import BenchmarkError, BenchmarkPlan, run_sequential

    trained = _fake_training(monkeypatch)
    grid = {"preset": "smoke", "envs": ("env_1",), "algos": ("ppo", "dqn")}
    out = tmp_path / "b"
    run_sequential(BenchmarkPlan(**grid, seeds=1), out)
    assert trained == ["env_1__ppo__0__bench", "env_1__dqn__0__bench"]
    first = (out / "runs" / "env_1__ppo__0__bench" / "config.yaml").stat().st_mtime_ns
    with pytest.raises(BenchmarkError, match="already holds a benchmark"):
        run_sequential(BenchmarkPlan(**grid, seeds=3), out)  # without --resume
    with pytest.raises(BenchmarkError, match="only --seeds may grow"):
        run_sequential(BenchmarkPlan(**grid, seeds=3, agents=3), out, resume=True)
    reported = []
    done = run_sequential(BenchmarkPlan(**grid, seeds=3), out, resume=True, progress=reported.append)
    assert trained[2:] == [f"env_1__{a}__{s}__bench" for a in ("ppo", "dqn") for s in (1, 2)]
    assert reported == trained[2:]  # the kept seed-0 runs are not reported as trained
    assert len(done) == 6 and all(path.exists() for path in done.values())
    assert (out / "runs" / "env_1__ppo__0__bench" / "config.yaml").stat().st_mtime_ns == first
    assert json.loads((out / "benchmark.json").read_text())["seeds"] == 3
    # fewer seeds than saved is another plan, not a resume
    with pytest.raises(BenchmarkError, match="only --seeds may grow"):
        run_sequential(BenchmarkPlan(**grid, seeds=2), out, resume=True)


def test_benchmark_command_counts_kept_runs_apart_from_trained_ones(tmp_path, monkeypatch, capsys):
    from eval.cli import main

    _fake_training(monkeypatch)
    args = ["benchmark", "--preset", "smoke", "--envs", "env_1", "--algos", "ppo", "dqn", "--no-ray",
            "--train-only", "--out", str(tmp_path / "b")]
    assert main([*args, "--seeds", "1"]) == 0
    assert "trained 2 trials" in capsys.readouterr().out
    assert main([*args, "--seeds", "3", "--resume"]) == 0
    out = capsys.readouterr().out
    assert "6 trials (2 finished earlier, kept)" in out
    assert "trained 4 trials" in out and "trained env_1__ppo__0__bench" not in out


def test_a_resumed_ray_grid_counts_trials_at_their_budget_as_kept(tmp_path, monkeypatch, capsys):
    """Tune moves finished runs into runs/ only when the whole grid ends: a grid cut before that
    has finished trials in trials/<cell> at their budget; the resume's first line counts them
    (it said "0 finished earlier" with two finished), and its last counts only what it trained."""
    from eval.cli import main
    from eval.scale import benchmark, raysession
    from eval.scale.benchmark import BenchmarkPlan, _prepare, cell_name, finished_cells

    out = tmp_path / "b"
    plan = BenchmarkPlan(preset="smoke", envs=("env_1",), algos=("ppo", "dqn"), seeds=2)
    _prepare(plan, out, resume=False)
    cells = {cell_name(c): c.steps for c in plan.cells()}
    ppo0, ppo1, dqn0 = "env_1__ppo__0__bench", "env_1__ppo__1__bench", "env_1__dqn__0__bench"
    for name, steps, where in ((ppo0, cells[ppo0], "runs"), (ppo1, cells[ppo1], "trials"),
                               (dqn0, cells[dqn0] - 1, "trials")):
        run = out / where / name / ("" if where == "runs" else f"{name}-1")
        run.mkdir(parents=True)
        (run / "state.json").write_text(json.dumps({"env_steps": steps}))
    assert finished_cells(plan, out) == [ppo0, ppo1]  # dqn0 is one step short; dqn1 never started

    monkeypatch.setattr(raysession, "ray_available", lambda: True)
    monkeypatch.setattr(benchmark, "run_ray", lambda plan, out, **_: {cell_name(c): out / "runs" / cell_name(c)
                                                                       for c in plan.cells()})
    assert main(["benchmark", "--preset", "smoke", "--envs", "env_1", "--algos", "ppo", "dqn", "--seeds", "2",
                 "--train-only", "--resume", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "4 trials (2 finished earlier, kept)" in said and "trained 2 trials" in said


def test_a_grid_from_a_first_seed_trains_the_same_cells_as_the_whole_grid(tmp_path, monkeypatch, capsys):
    """--first-seed 1 --seeds 2: the cells "seed 1" and "seed 2" of a grid from seed 0, with
    the same configs; the plan records it (a plan saved before it reads back as equal) and a
    resume with more seeds grows from it."""
    from eval.cli import main
    from eval.scale.benchmark import BenchmarkError, BenchmarkPlan

    grid = {"preset": "smoke", "envs": ("env_1", "env_2"), "algos": ("ppo", "dqn")}
    whole, part = BenchmarkPlan(**grid, seeds=3), BenchmarkPlan(**grid, seeds=2, first_seed=1)
    assert list(part.seed_list) == [1, 2]
    assert [c.to_dict() for c in part.cells()] == [c.to_dict() for c in whole.cells() if c.seed >= 1]
    assert part.to_dict() == {**BenchmarkPlan(**grid, seeds=2).to_dict(), "first_seed": 1}
    assert "first_seed" not in whole.to_dict()
    with pytest.raises(BenchmarkError, match="--first-seed must be >= 0, got -1"):
        BenchmarkPlan(first_seed=-1)

    trained = _fake_training(monkeypatch)
    args = ["benchmark", "--preset", "smoke", "--envs", "env_1", "--algos", "ppo", "--no-ray",
            "--train-only", "--out", str(tmp_path / "b"), "--first-seed", "1"]
    assert main([*args, "--seeds", "1"]) == 0
    assert trained == ["env_1__ppo__1__bench"]
    assert main([*args, "--seeds", "2", "--resume"]) == 0
    assert trained == ["env_1__ppo__1__bench", "env_1__ppo__2__bench"]
    assert json.loads((tmp_path / "b" / "benchmark.json").read_text())["first_seed"] == 1
    # another first seed on the same folder is another plan
    assert main([*args[:-1], "2", "--seeds", "2", "--resume"]) == 2
    assert "only --seeds may grow" in capsys.readouterr().err


def test_more_seeds_wait_for_the_saved_benchmark_to_finish(tmp_path):
    from eval.scale.benchmark import BenchmarkError, BenchmarkPlan, _prepare

    grid = {"preset": "smoke", "envs": ("env_1",), "algos": ("ppo",)}
    out = tmp_path / "b"
    assert _prepare(BenchmarkPlan(**grid, seeds=2), out, resume=False) is False
    (out / "runs" / "env_1__ppo__0__bench").mkdir(parents=True)  # seed 1 never finished
    with pytest.raises(BenchmarkError, match=r"unfinished \(env_1__ppo__1__bench.*--resume --seeds 2"):
        _prepare(BenchmarkPlan(**grid, seeds=3), out, resume=True)
    assert json.loads((out / "benchmark.json").read_text())["seeds"] == 2  # left as it was
    (out / "runs" / "env_1__ppo__1__bench").mkdir()
    assert _prepare(BenchmarkPlan(**grid, seeds=3), out, resume=True) is True
    assert _prepare(BenchmarkPlan(**grid, seeds=3), out, resume=True) is False  # saved now


def test_commands_without_a_grid_never_import_ray():
    code = ("import sys, eval.cli, eval.scale.benchmark, eval.scale.pbt, eval.scale.raysession; "
            "eval.cli.build_parser().parse_args(['benchmark', '--no-ray']); "
            "eval.scale.raysession.ray_available(); assert 'ray' not in sys.modules, 'ray imported'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_benchmark_without_ray_says_how_to_install(monkeypatch, capsys, tmp_path):
    import eval.scale.raysession
    from eval.cli import main

    monkeypatch.setattr(eval.scale.raysession, "ray_available", lambda: False)
    assert main(["benchmark", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install -e '.[tune]'" in err
    assert main(["train", "--algo", "ppo", "--pbt", "4", "--out", str(tmp_path)]) == 2
    assert "pip install -e '.[tune]'" in capsys.readouterr().err


def test_pbt_mutations_are_fields_of_each_agent_config():
    from eval.scale.pbt import MUTATIONS, mutation_space, with_hyper
    from eval.training.train import make_config

    for algo in MUTATIONS:
        cfg = make_config(algo, "env_1", "quick")
        space = mutation_space(algo, cfg.agent_config)
        assert space and all(len(v) >= 3 for v in space.values()), (algo, space)
        for name, values in space.items():  # every value is valid for the agent's config class
            for value in values:
                changed = with_hyper(cfg, {name: value}).agent_config
                assert type(changed) is type(cfg.agent_config) and getattr(changed, name) == value


# -- Ray -------------------------------------------------------------------------------
@needs_ray
def test_ray_address_that_does_not_answer_fails_within_seconds(tmp_path):
    port = free_port()
    for args in (["benchmark", "--envs", "env_1", "--algos", "ppo", "--out", str(tmp_path / "b")],
                 ["train", "--algo", "ppo", "--pbt", "2", "--out", str(tmp_path / "p")]):
        start = time.monotonic()
        done = cosim([*args, "--ray-address", f"127.0.0.1:{port}"], timeout=60)
        # python + torch imports included (25 s seen on a loaded 2-core machine, nice 10);
        # Ray's own retry would take ~60 s and the call's timeout is 60
        assert time.monotonic() - start < 45
        assert done.returncode == 2, done.stderr
        assert f"no Ray cluster answers at 127.0.0.1:{port}" in done.stderr
        assert "ray start --head" in done.stderr
    bad = cosim(["benchmark", "--ray-address", "nonsense", "--out", str(tmp_path / "c")], timeout=60)
    assert bad.returncode == 2 and "write HOST:PORT" in bad.stderr


def _checkpoints(tune_dir: Path) -> dict[tuple[str, int], Path]:
    """(trial, env_steps) -> the Tune checkpoint (a run folder) that trial reported then."""
    out = {}
    for meta in tune_dir.glob("*/checkpoint_*/pbt_trial.json"):
        m = json.loads(meta.read_text())
        if meta.parent.parent.name == m["trial"]:
            out[(m["trial"], m["env_steps"])] = meta.parent
    return out


def _return_at(checkpoint: Path) -> float:
    return json.loads((checkpoint / "pbt_trial.json").read_text())["mean_return"]


@needs_ray
@pytest.mark.cluster  # a PBT run on Ray (~90 s): .ci/run runs it in its -m cluster step
@pytest.mark.timeout(1000)  # the run's own budget is 900 s (2 min on a quiet machine, ~10 at load 13)
def test_pbt_exploits_continue_from_the_donor_checkpoint_with_perturbed_hyperparameters(tmp_path, ray_tmp):
    import pandas as pd
    import torch

    from eval.scale.pbt import weights_digest
    from eval.testing import selection
    from eval.testing.loading import load_for_slot

    done = cosim(["train", "--algo", "ppo", "--env", "env_1", "--preset", "smoke", "--steps",
                  str(PBT_STEPS), "--pbt", "4", "--pbt-interval", str(PBT_INTERVAL), "--out",
                  str(tmp_path)], ray_tmp, timeout=900)  # a hang fails; a loaded machine does not
    assert done.returncode == 0, done.stderr[-3000:]
    (folder,) = tmp_path.glob("env_1__ppo__0__pbt4-*")
    lineage = pd.read_csv(folder / "lineage.csv")
    assert (folder / "lineage.png").stat().st_size > 10_000
    exploits = lineage.drop_duplicates(["env_steps", "trial"])
    assert len(exploits) >= 1, "no exploit happened"
    assert set(lineage["parameter"]) == {"learning_rate", "ent_coef", "clip_coef", "gae_lambda"}
    ckpts = _checkpoints(folder / "pbt" / "tune" / "pbt")
    checked = distinct = 0
    for e in exploits.itertuples():
        rows = lineage[(lineage.env_steps == e.env_steps) & (lineage.trial == e.trial)]
        assert rows["perturbed"].any(), f"exploit of {e.trial} at {e.env_steps}: nothing perturbed"
        donor_ckpt = ckpts[(e.donor, e.env_steps)]
        # the weights resumed are the donor's at that step, not the clone's own
        donor = weights_digest(donor_ckpt / "checkpoints/ac_0/latest.pt")
        assert e.donor_weights_sha256 == donor and e.resumed_weights_sha256 == donor
        own = ckpts.get((e.trial, e.env_steps))
        if own is not None and _return_at(own) != _return_at(donor_ckpt):
            # a different score means a different past; equal weights would mean the clone
            # kept its own. (Equal scores happen: a trial that cloned this donor before and
            # whose AC made no PPO update since holds the donor's weights; nothing to tell.)
            assert weights_digest(own / "checkpoints/ac_0/latest.pt") != donor
            distinct += 1
        after = ckpts.get((e.trial, e.env_steps + PBT_INTERVAL))
        if after is None:  # cloned at the final step
            continue
        # the step counter and the episode history continue from the donor's
        assert json.loads((after / "state.json").read_text())["env_steps"] == e.env_steps + PBT_INTERVAL
        donor_rows = (donor_ckpt / "episodes.csv").read_text().splitlines()
        assert (after / "episodes.csv").read_text().splitlines()[: len(donor_rows)] == donor_rows
        # the perturbed hyperparameters are the ones trained with: config and optimizer
        new = dict(zip(rows.parameter, rows.new_value, strict=True))
        agent_config = yaml.safe_load((after / "config.yaml").read_text())["agent_config"]
        assert agent_config["learning_rate"] == pytest.approx(new["learning_rate"])
        payload = torch.load(after / "checkpoints/ac_0/latest.pt", weights_only=True)
        assert payload["config"]["ent_coef"] == pytest.approx(new["ent_coef"])
        lr = payload["state"]["optimizers"]["optimizer"]["param_groups"][0]["lr"]
        assert lr == pytest.approx(new["learning_rate"])
        checked += 1
    assert checked >= 1, "no exploit before the final step to follow"
    assert distinct >= 1, "no exploit of a trial whose own weights differed from the donor's"
    # the best trial is a normal run folder that `cosim test` loads
    chosen = selection.choose(folder)
    assert chosen is not None and load_for_slot(chosen.path, "ppo") is not None
    assert len(pd.read_csv(folder / "trials.csv")) == 4


BENCH = ["benchmark", "--preset", "smoke", "--envs", "env_1", "--algos", "ppo", "dqn", "td3",
         "--steps", "80"]


@needs_ray
@pytest.mark.slow  # ~50 s: with the PBT test the default run would pass its ~2 minute budget
def test_benchmark_with_ray_and_without_gives_the_same_checkpoints(tmp_path, ray_tmp):
    # --keep all: a finished run keeps latest.pt (weights, optimiser moments, targets) to compare
    with_ray = cosim([*BENCH, "--train-only", "--keep", "all", "--concurrent", "2", "--out",
                      str(tmp_path / "ray")], ray_tmp)
    assert with_ray.returncode == 0, with_ray.stderr[-3000:]
    without = cosim([*BENCH, "--train-only", "--keep", "all", "--no-ray", "--out", str(tmp_path / "seq")])
    assert without.returncode == 0, without.stderr[-3000:]
    files = sorted((tmp_path / "ray" / "runs").glob("*/checkpoints/ac_*/latest.pt"))
    assert len(files) == 3 * 2  # three cells, two ACs each
    for path in files:
        other = tmp_path / "seq" / path.relative_to(tmp_path / "ray")
        a, b = tensors(path), tensors(other)
        assert a.keys() == b.keys() and a
        different = [k for k in a if not (a[k] == b[k]).all()]
        assert not different, f"{path.relative_to(tmp_path)}: {different[:3]}"
        assert json.loads((path.parents[2] / "state.json").read_text())["env_steps"] == 80


@needs_ray
@pytest.mark.slow
def test_benchmark_writes_the_report_in_one_command(tmp_path, ray_tmp):
    done = cosim([*BENCH, "--seeds", "2", "--out", str(tmp_path / "b")], ray_tmp)
    assert done.returncode == 0, done.stderr[-3000:]
    report = tmp_path / "b" / "report"
    for name in ("index.html", "rq1.md", "provenance.json"):
        assert (report / name).exists(), name
    import pandas as pd

    # the two seeds' test episodes stay apart (one smoke episode each, one AC per algorithm)
    per = pd.read_csv(report / "episodes.csv")
    counts = per[per.scenario == 1].groupby("algorithm").size()
    assert counts.to_dict() == {"dqn": 2, "ppo": 2, "td3": 2}, counts
    rq1 = (report / "rq1.md").read_text()
    assert all(algo.upper() in rq1.upper() for algo in ("ppo", "dqn", "td3"))
    assert "Benchmark grid" in (report / "index.md").read_text()
    # two seeds: the statistics over seeds (eval/reporting/multiseed.py), one row per pair
    assert "## Over training seeds" in (report / "index.md").read_text()
    assert len(pd.read_csv(report / "verdict.csv")) == 3 and len(pd.read_csv(report / "budget.csv")) == 3 * 2
    # issue 28: every environment's and seed's checkpoints in provenance, the reference columns
    prov = json.loads((report / "provenance.json").read_text())
    assert len(prov["checkpoints"]) == 3 * 2 and prov["benchmark"]["preset"] == "smoke"
    assert "S1 autopilot (ref)" in rq1 and "| return |" in rq1


@needs_ray
@pytest.mark.slow
@pytest.mark.parametrize("tune_state", ["kept", "lost"])
def test_ctrl_c_leaves_no_ray_process_and_resume_continues(tmp_path, ray_tmp, tune_state):
    """``lost``: Tune's experiment is deleted before the resume (the way to change a preset
    mid-grid, docs/guide.md): the new grid finds each cell's run in trials/ and continues it."""
    out = tmp_path / "b"
    args = ["benchmark", "--preset", "smoke", "--envs", "env_1", "--algos", "ppo", "dqn",
            "--steps", "160", "--concurrent", "1", "--train-only", "--out", str(out)]
    env = {**os.environ, "RAY_TMPDIR": str(ray_tmp)}
    proc = subprocess.Popen([sys.executable, "-m", "eval.cli", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    grid = out / "tune" / "grid"
    deadline = time.monotonic() + 300
    # interrupt once the first trial finished and the second has a checkpoint
    def reports(cell: str) -> int:
        path = grid / cell / "result.json"
        return len(path.read_text().splitlines()) if path.exists() else 0

    while time.monotonic() < deadline and not (reports("env_1__ppo__0__bench") >= 4
                                               and reports("env_1__dqn__0__bench") >= 1):
        time.sleep(0.5)
    first = grid / "env_1__ppo__0__bench" / "result.json"  # one line per report
    assert first.exists() and proc.poll() is None
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal sends: the whole group
    log, _ = proc.communicate(timeout=120)
    assert proc.returncode != 0, log[-2000:]
    assert "--resume" in log
    assert not wait_gone(ray_tmp), "Ray processes left after Ctrl-C"
    finished = first.read_text()
    ppo_state = (out / "runs" / "env_1__ppo__0__bench" / "state.json").read_text()  # exported at Ctrl-C
    if tune_state == "lost":
        shutil.rmtree(grid)
    resumed = cosim([*args, "--resume"], ray_tmp)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    if tune_state == "lost":  # PPO's finished run kept as it was; DQN's went on from its checkpoint
        assert (out / "runs" / "env_1__ppo__0__bench" / "state.json").read_text() == ppo_state
        nodes = (out / "runs" / "env_1__dqn__0__bench" / "trial_nodes.jsonl").read_text().splitlines()
        assert len(nodes) == 2 and json.loads(nodes[1])["env_steps"] > json.loads(nodes[0])["env_steps"]
        return
    assert first.read_text() == finished  # the finished trial was not trained again
    # the restored grid says when its trial ends, once, counting the one finished before
    assert resumed.stdout.count("trained env_1__dqn__0__bench") == 1, resumed.stdout
    assert "[2/2] trained env_1__dqn__0__bench" in resumed.stdout
    for cell in ("env_1__ppo__0__bench", "env_1__dqn__0__bench"):
        assert json.loads((out / "runs" / cell / "state.json").read_text())["env_steps"] == 160


@needs_ray
@pytest.mark.slow
def test_resume_with_more_seeds_on_ray_keeps_the_finished_runs(tmp_path, ray_tmp):
    out = tmp_path / "b"
    args = ["benchmark", "--preset", "smoke", "--envs", "env_1", "--algos", "ppo", "--steps", "80",
            "--concurrent", "1", "--train-only", "--out", str(out)]
    assert cosim(args, ray_tmp).returncode == 0
    state = out / "runs" / "env_1__ppo__0__bench" / "state.json"
    before = state.stat().st_mtime_ns
    more = cosim([*args, "--seeds", "2", "--resume"], ray_tmp)
    assert more.returncode == 0, more.stderr[-3000:]
    assert state.stat().st_mtime_ns == before  # seed 0 was not trained again
    assert json.loads((out / "runs" / "env_1__ppo__1__bench" / "state.json").read_text())["env_steps"] == 80
    assert sorted(p.name for p in (out / "tune" / "grid").iterdir() if p.is_dir()) == ["env_1__ppo__1__bench"]


@needs_ray
@pytest.mark.slow
def test_ray_start_head_on_loopback_and_benchmark_on_it(tmp_path, ray_tmp):
    import secrets

    port = free_port()
    # a head on loopback only, with token authentication; the driver joins it as docs/guide.md
    # says: RAY_AUTH_MODE=token and the head's token (here in RAY_AUTH_TOKEN on both sides)
    token = secrets.token_hex(32)
    auth = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token}
    env = {**os.environ, "RAY_TMPDIR": str(ray_tmp), "RAY_USAGE_STATS_ENABLED": "0",
           "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", **auth}
    ray_bin = Path(sys.executable).with_name("ray")
    start = subprocess.run([str(ray_bin), "start", "--head", "--node-ip-address", "127.0.0.1",
                            "--port", str(port), "--num-cpus", "2", "--include-dashboard", "false",
                            "--disable-usage-stats"], env=env, capture_output=True, text=True,
                           timeout=120)
    try:
        assert start.returncode == 0, start.stderr[-2000:]
        listening = subprocess.run(["ss", "-ltnp"], capture_output=True, text=True).stdout
        ours = [line for line in listening.splitlines() if f":{port} " in line]
        assert ours and all("127.0.0.1]:" in line or " 127.0.0.1:" in line for line in ours), ours
        done = cosim(["benchmark", "--preset", "smoke", "--envs", "env_1", "--algos", "ppo",
                      "--steps", "40", "--train-only", "--ray-address", f"127.0.0.1:{port}",
                      "--out", str(tmp_path / "b")], ray_tmp, env_extra=auth)
        assert done.returncode == 0, done.stderr[-3000:]
        # the token without RAY_AUTH_MODE=token (unset acts the same for an explicit address):
        # Ray 2.60 does not send it, the head refuses, and the message says what to set
        refused = cosim(["benchmark", "--envs", "env_1", "--algos", "ppo", "--ray-address",
                         f"127.0.0.1:{port}", "--out", str(tmp_path / "c")], ray_tmp,
                        env_extra={"RAY_AUTH_MODE": "disabled", "RAY_AUTH_TOKEN": token}, timeout=180)
        assert refused.returncode == 2, refused.stderr[-2000:]
        assert "RAY_AUTH_MODE=token" in refused.stderr.strip().splitlines()[-1]
        assert (tmp_path / "b" / "runs" / "env_1__ppo__0__bench" / "checkpoints").exists()
    finally:  # the head's processes, by PID (never `ray stop`: it stops every Ray on the machine)
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for pid in ray_pids(ray_tmp):
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + 10
            while ray_pids(ray_tmp) and time.monotonic() < deadline:
                time.sleep(0.5)


def stop_processes(pids: list[int]) -> None:
    """SIGTERM then SIGKILL the given processes, waiting up to 10 s for them to go."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + 10
        while any(Path(f"/proc/{pid}").exists() and "\nState:\tZ" not in _status(pid) for pid in pids) \
                and time.monotonic() < deadline:
            time.sleep(0.3)


def _status(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return "\nState:\tZ"


def pids_with_env(entry: str) -> list[int]:
    """PIDs of live processes whose environment holds ``entry`` (``NAME=value``)."""
    needle = f"{entry}\0".encode()
    found = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit() and int(proc.name) != os.getpid():
            try:
                if needle in (proc / "environ").read_bytes() and "\nState:\tZ" not in _status(int(proc.name)):
                    found.append(int(proc.name))
            except OSError:
                continue
    return found


def _reports(result_json: Path) -> list[dict]:
    """The Tune results a trial reported so far (one JSON line per checkpoint)."""
    if not result_json.exists():
        return []
    lines = result_json.read_text().splitlines()
    return [json.loads(line) for line in lines if line.strip().endswith("}")]


# Two Ray nodes on this machine (docs/guide.md#scale-out-a-cluster-of-several-machines): Ray rewrites 127.0.0.1 to the
# machine's routable address once clusters are enabled, so the head takes another
# loopback address; every node listens on all interfaces then, hence token authentication.
HEAD_IP, WORKER_IP = "127.0.0.3", "127.0.0.2"
CLUSTER_STEPS = 80  # two checkpoints (smoke: every 40 steps): the node dies between them


@needs_ray
@pytest.mark.cluster
@pytest.mark.timeout(1500)
def test_two_node_cluster_spreads_trials_survives_a_node_kill_and_matches_no_ray(tmp_path, ray_tmp):
    """`cosim benchmark --ray-address` on a head and a worker node: one trial per node, the
    worker node killed (SIGKILL, every process of it) after its trial's first checkpoint;
    the trial resumes on the head from that checkpoint, the report is complete, and the
    trial no node loss touched is bit-identical to `--no-ray`'s."""
    import secrets

    import pandas as pd

    port = free_port()
    token = secrets.token_hex(32)
    env = {**os.environ, "RAY_TMPDIR": str(ray_tmp), "RAY_USAGE_STATS_ENABLED": "0",
           "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "1", "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token}
    marker = f"COSIM_TEST_NODE={ray_tmp.name}-worker"  # every process of the worker node inherits it
    ray_bin = str(Path(sys.executable).with_name("ray"))
    # one CPU per node and one per trial (smoke: one env each): one trial on each node
    common = ["--num-cpus", "1", "--disable-usage-stats"]
    out, seq = tmp_path / "b", tmp_path / "seq"
    grid = ["benchmark", "--preset", "smoke", "--envs", "env_1", "--algos", "ppo", "dqn",
            "--steps", str(CLUSTER_STEPS), "--keep", "all"]
    proc = None
    try:
        head = subprocess.run([ray_bin, "start", "--head", "--node-ip-address", HEAD_IP, "--port", str(port),
                               "--include-dashboard", "false", *common], env=env, capture_output=True,
                              text=True, timeout=180)
        assert head.returncode == 0, head.stderr[-2000:]
        worker = subprocess.run([ray_bin, "start", "--address", f"{HEAD_IP}:{port}", "--node-ip-address",
                                 WORKER_IP, *common], env={**env, marker.split("=")[0]: marker.split("=")[1]},
                                capture_output=True, text=True, timeout=180)
        assert worker.returncode == 0, worker.stderr[-2000:]
        assert pids_with_env(marker), "no process of the worker node"
        proc = subprocess.Popen([sys.executable, "-m", "eval.cli", *grid, "--concurrent", "2",
                                 "--ray-address", f"{HEAD_IP}:{port}", "--out", str(out)],
                                env={**env, "PYTHONUNBUFFERED": "1"}, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, start_new_session=True)
        cells = ("env_1__ppo__0__bench", "env_1__dqn__0__bench")
        # wait for the trial on the worker node to report its first checkpoint, then kill that node
        killed = None
        deadline = time.monotonic() + 900
        while killed is None and proc.poll() is None and time.monotonic() < deadline:
            for cell in cells:
                if any(r.get("node_ip") == WORKER_IP for r in _reports(out / "tune" / "grid" / cell / "result.json")):
                    killed = cell
            time.sleep(0.3)
        assert killed is not None, f"no trial reported from {WORKER_IP}: " + (proc.stdout.read()[-3000:]
                                                                             if proc.poll() is not None else "")
        stop_processes(pids_with_env(marker))
        assert not pids_with_env(marker)
        before = _reports(out / "tune" / "grid" / killed / "result.json")
        assert max(r["env_steps"] for r in before) < CLUSTER_STEPS, "the trial finished before the kill"
        log, _ = proc.communicate(timeout=900)
        assert proc.returncode == 0, log[-4000:]
    finally:
        if proc is not None and proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        # the head's and any worker's processes, by PID (never `ray stop`: it stops every Ray here)
        stop_processes(ray_pids(ray_tmp))

    (spared,) = set(cells) - {killed}
    # which node trained which trial: Tune's results and each run folder's trial_nodes.jsonl
    ips = {cell: [r["node_ip"] for r in _reports(out / "tune" / "grid" / cell / "result.json")] for cell in cells}
    assert set(ips[spared]) == {HEAD_IP} and ips[killed][0] == WORKER_IP and ips[killed][-1] == HEAD_IP, ips
    nodes = {cell: [json.loads(line) for line in (out / "runs" / cell / "trial_nodes.jsonl").read_text().splitlines()]
             for cell in cells}
    assert [n["node_ip"] for n in nodes[spared]] == [HEAD_IP]
    assert [n["node_ip"] for n in nodes[killed]] == [WORKER_IP, HEAD_IP]
    assert nodes[killed][0]["node_id"] != nodes[killed][1]["node_id"]
    # resumed from its checkpoint (40 steps), not from scratch: its first report on the head is at 80
    assert nodes[killed][1]["env_steps"] == CLUSTER_STEPS
    for cell in cells:  # nothing lost: every trial at its budget, every AC's checkpoints there
        assert json.loads((out / "runs" / cell / "state.json").read_text())["env_steps"] == CLUSTER_STEPS
        assert len(list((out / "runs" / cell / "checkpoints").glob("ac_*/latest.pt"))) == 2
    # the report is complete: both algorithms tested
    per = pd.read_csv(out / "report" / "episodes.csv")
    assert set(per["algorithm"]) == {"ppo", "dqn"} and (out / "report" / "index.html").exists()

    # the same grid without Ray: the trial no node loss touched is bit-identical
    without = cosim([*grid, "--train-only", "--no-ray", "--out", str(seq)])
    assert without.returncode == 0, without.stderr[-3000:]
    for path in sorted((out / "runs" / spared).glob("checkpoints/ac_*/latest.pt")):
        a, b = tensors(path), tensors(seq / path.relative_to(out))
        assert a.keys() == b.keys() and a
        assert not [k for k in a if not (a[k] == b[k]).all()], path
    a, b = (pd.read_csv(root / "runs" / spared / "episodes.csv").drop(columns="wall_time_s") for root in (out, seq))
    pd.testing.assert_frame_equal(a, b)


@needs_ray
@pytest.mark.cluster  # 87-93 s at load ~4, 139-224 s at 10-13; the scheduler's part runs by default (test_pbt_scheduler.py)
@pytest.mark.timeout(1000)
def test_ctrl_c_during_pbt_leaves_no_ray_process_and_resume_finishes_it(tmp_path, ray_tmp):
    args = ["train", "--algo", "ppo", "--env", "env_1", "--preset", "smoke", "--steps", "240",
            "--pbt", "2", "--pbt-interval", "60", "--out", str(tmp_path)]
    env = {**os.environ, "RAY_TMPDIR": str(ray_tmp)}
    proc = subprocess.Popen([sys.executable, "-m", "eval.cli", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and sum(
            len(p.read_text().splitlines()) for p in tmp_path.glob("*/pbt/history/*.jsonl")) < 3:
        time.sleep(0.5)
    assert proc.poll() is None
    os.killpg(proc.pid, signal.SIGINT)
    log, _ = proc.communicate(timeout=120)
    assert proc.returncode != 0 and "--resume" in log, log[-2000:]
    assert not wait_gone(ray_tmp), "Ray processes left after Ctrl-C"
    (folder,) = tmp_path.glob("env_1__ppo__0__pbt2-*")
    assert not (folder / "lineage.csv").exists()
    exploits_before = {p.name: p.read_text() for p in (folder / "pbt" / "exploits").glob("*.json")}
    resumed = cosim(["train", "--resume", str(folder)], ray_tmp, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert (folder / "lineage.csv").exists() and (folder / "lineage.png").exists()
    assert json.loads((folder / "state.json").read_text())["env_steps"] == 240
    assert_lineage_intact(folder, exploits_before, population=2, interval=60, steps=240)


def assert_lineage_intact(folder: Path, exploits_before: dict[str, str], population: int,
                          interval: int, steps: int) -> None:
    """After a resume the PBT lineage is whole: the exploits recorded before the interruption
    are kept unchanged and in lineage.csv, every trial reported at every barrier once
    (no gap, no step trained twice kept), and every exploit cloned a live trial's weights
    at a barrier."""
    import pandas as pd

    from eval.scale.pbt import _histories

    exploits = {p.name: p.read_text() for p in (folder / "pbt" / "exploits").glob("*.json")}
    assert {k: exploits.get(k) for k in exploits_before} == exploits_before, "an exploit record was lost or rewritten"
    # two trials: the lower one clones the upper one at every barrier, so the resumed run exploits too
    assert len(exploits) > len(exploits_before), "no exploit after the resume"
    lineage = pd.read_csv(folder / "lineage.csv")
    events = {(e["env_steps"], e["trial"]) for e in map(json.loads, exploits.values())}
    assert set(zip(lineage.env_steps, lineage.trial, strict=True)) == events
    histories = _histories(folder)
    assert len(histories) == population
    barriers = list(range(interval, steps + 1, interval))
    for trial, points in histories.items():
        assert [p["env_steps"] for p in points] == barriers, (trial, [p["env_steps"] for p in points])
    for e in lineage.drop_duplicates(["env_steps", "trial"]).itertuples():
        assert e.env_steps in barriers and e.donor in histories and e.donor != e.trial
        assert e.donor_weights_sha256 == e.resumed_weights_sha256  # the donor's weights, cloned
    assert len(pd.read_csv(folder / "trials.csv")) == population


def test_a_tune_folder_from_before_the_subpackages_is_refused_with_what_to_do(tmp_path):
    """Tune's tuner.pkl names the trainable's and the scheduler's modules; those of a folder
    written before eval/ was split (issue 26) no longer import: one clear error, not a traceback."""
    from eval.scale.raysession import RayError, refuse_old_layout

    refuse_old_layout(tmp_path)  # nothing to restore
    for new in (b"eval.scale.benchmark\x94_tune_trial", b"eval.scale.pbt_scheduler\x94ResumablePBT"):
        (tmp_path / "tuner.pkl").write_bytes(b"\x80\x05" + new)
        refuse_old_layout(tmp_path)
    for old in (b"eval.benchmark\x94_tune_trial", b"eval.pbt\x94_pbt_trial", b"eval.pbt_scheduler\x94ResumablePBT"):
        (tmp_path / "tuner.pkl").write_bytes(b"\x80\x05" + old)
        with pytest.raises(RayError, match="before eval/ was split"):
            refuse_old_layout(tmp_path)


def test_the_plan_records_the_obs_and_sharing_variants_and_shares_where_it_can():
    from eval.scale.benchmark import BenchmarkError, BenchmarkPlan

    plan = BenchmarkPlan(preset="smoke", envs=("env_1",), algos=("ppo", "a3c", "td3"), obs="nav",
                         share_params=True)
    cells = {c.algo: c for c in plan.cells()}
    assert {a: (c.obs, c.share_params) for a, c in cells.items()} == {
        "ppo": ("nav", True), "a3c": ("nav", False), "td3": ("nav", True)}
    assert {"obs": "nav", "share_params": True}.items() <= plan.to_dict().items()
    default = BenchmarkPlan(preset="smoke", envs=("env_1",), algos=("ppo",)).to_dict()
    assert "obs" not in default and "share_params" not in default  # old plans still read as equal
    with pytest.raises(BenchmarkError, match="--obs must be image or nav"):
        BenchmarkPlan(preset="smoke", obs="lidar")


def test_the_demonstration_variant_reaches_only_the_replay_learners():
    """--demo-steps: DQN, DDPG and TD3 trials get the demonstrations, the pre-training and the
    variant's losses; PPO and A3C trials are the plain grid's; the plan records it only when set."""
    from eval.scale.benchmark import BenchmarkError, BenchmarkPlan
    from eval.training.config import DEMO_UPDATES

    algos = ("ppo", "a3c", "dqn", "td3")
    plain = {c.algo: c for c in BenchmarkPlan(preset="smoke", envs=("env_2",), algos=algos).cells()}
    cells = {c.algo: c for c in BenchmarkPlan(preset="smoke", envs=("env_2",), algos=algos,
                                              demo_steps=300).cells()}
    assert {a: (c.demo_steps, c.demo_updates) for a, c in cells.items()} == {
        "ppo": (0, 0), "a3c": (0, 0), "dqn": (300, DEMO_UPDATES), "td3": (300, DEMO_UPDATES)}
    assert cells["ppo"] == plain["ppo"] and cells["a3c"] == plain["a3c"]
    assert cells["dqn"].agent_config.demo_margin == 0.8 and plain["dqn"].agent_config.demo_margin == 0
    assert cells["dqn"].agent_config.exploration_initial_eps == 0.1
    assert cells["td3"].agent_config.demo_bc == 1.0 and plain["td3"].agent_config.demo_bc == 0
    assert BenchmarkPlan(preset="smoke", demo_steps=300).to_dict()["demo_steps"] == 300
    assert "demo_steps" not in BenchmarkPlan(preset="smoke").to_dict()  # old plans still read as equal
    with pytest.raises(BenchmarkError, match="--demo-steps must be >= 0"):
        BenchmarkPlan(preset="smoke", demo_steps=-1)


def test_a_new_grid_continues_only_runs_of_the_same_config(tmp_path):
    import dataclasses

    from eval.scale.benchmark import BenchmarkPlan, earlier_run

    cfg = BenchmarkPlan(preset="smoke", envs=("env_1",), algos=("dqn",)).cells()[0]
    other = dataclasses.replace(cfg, agent_config=dataclasses.replace(cfg.agent_config, train_freq=8))

    def run(name: str, c, state: bool = True) -> Path:
        folder = tmp_path / "cell" / name
        folder.mkdir(parents=True)
        (folder / "config.yaml").write_text(yaml.safe_dump(c.to_dict(), sort_keys=False))
        if state:
            (folder / "state.json").write_text(json.dumps({"env_steps": 40}))
        return folder

    assert earlier_run(tmp_path / "cell", cfg) is None
    same = run("env_1__dqn__0__20261126-0900", cfg)
    run("env_1__dqn__0__20261126-1000", other)             # newer, another train_freq
    run("env_1__dqn__0__20261126-1100", cfg, state=False)  # newest, no checkpoint committed
    assert earlier_run(tmp_path / "cell", cfg) == same
    assert earlier_run(tmp_path / "cell", other).name.endswith("1000")


@needs_ray
def test_a_trial_whose_run_finished_before_reports_it_without_training(tmp_path, monkeypatch):
    # a session killed after a trial finished and before its export: the new grid's trial
    # finds the finished run in trials/<cell> and only tells Tune
    from ray import tune

    from eval.scale import benchmark

    cfg = benchmark.BenchmarkPlan(preset="smoke", envs=("env_1",), algos=("ppo",)).cells()[0]
    run = tmp_path / "trials" / benchmark.cell_name(cfg) / "env_1__ppo__0__20261126-0900"
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    (run / "state.json").write_text(json.dumps({"env_steps": cfg.steps}))
    reports = []
    monkeypatch.setattr(tune, "get_checkpoint", lambda: None)
    monkeypatch.setattr(tune, "report", lambda metrics, checkpoint: reports.append(
        (metrics, (Path(checkpoint.path) / benchmark.RUN_POINTER).read_text())))
    monkeypatch.setattr(benchmark, "_record_node", lambda run, steps: None)
    monkeypatch.setattr(benchmark, "train", lambda *a, **k: pytest.fail("trained a finished run"))
    benchmark._tune_trial({"cell": cfg.to_dict(), "scratch": str(tmp_path / "trials"), "keep": "best"})
    assert reports == [({"env_steps": cfg.steps, "mean_return": float("-inf")}, str(run.resolve()))]


def test_status_tells_finished_training_stopped_and_pending_trials_from_the_folder(tmp_path, capsys):
    from eval.cli import main
    from eval.scale.benchmark import BenchmarkPlan, _prepare, cell_name, finished_count
    from eval.scale.gridstatus import grid_status

    out = tmp_path / "b"
    plan = BenchmarkPlan(preset="smoke", envs=("env_1",), algos=("ppo", "dqn"), seeds=2)
    _prepare(plan, out, resume=False)
    budget = {cell_name(c): c.steps for c in plan.cells()}

    def run(where: Path, steps: int, seconds: float, best: dict, holder: int | None = None,
            commit: str = "a" * 40):
        where.mkdir(parents=True)
        (where / "config.yaml").write_text("algo: x\n")
        (where / "state.json").write_text(json.dumps({"env_steps": steps, "elapsed_s": seconds, "best": best}))
        (where / "run.lock").write_text(f"{holder}\n" if holder else "")
        (where / "manifest.json").write_text(json.dumps({"task_version": 3, "git": {"commit": commit}}))

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # a PID whose process is dead: a trial whose session ended
    ppo0, ppo1, dqn0 = "env_1__ppo__0__bench", "env_1__ppo__1__bench", "env_1__dqn__0__bench"
    run(out / "runs" / ppo0, budget[ppo0], 100.0, {"ac_0": 5.0, "ac_1": 7.5})
    run(out / "trials" / ppo1 / "env_1__ppo__1__20261126-0900", budget[ppo1] // 2, 40.0, {"ac_0": -3.0},
        holder=os.getpid())
    run(out / "trials" / dqn0 / "env_1__dqn__0__20261126-0900", 30, 15.0, {}, holder=gone.pid,
        commit="b" * 40)

    # the goal rate of each AC's latest 10 training episodes: ac_0 reached its last 10 goals
    # after 5 misses, ac_1 half of its 4
    rows = [("ac_0", 0)] * 5 + [("ac_0", 1)] * 10 + [("ac_1", 1), ("ac_1", 0)] * 2
    (out / "runs" / ppo0 / "episodes.csv").write_text(
        "agent,goal_reached\n" + "".join(f"{a},{bool(g)}\n" for a, g in rows))
    table = grid_status(out).set_index("cell")
    assert finished_count(out) == (1, 4)  # what the line per finished trial counts
    assert table.loc[ppo0, "goals"] == pytest.approx(12 / 14)
    assert table.state.to_dict() == {ppo0: "finished", ppo1: "training", dqn0: "stopped",
                                     "env_1__dqn__1__bench": "pending"}
    assert table.loc[ppo0, "best"] == 7.5 and table.loc[ppo1, "best"] == -3.0
    # learning left at the algorithm's median rate: PPO's two trials run at budget/100 and
    # budget/2/40 env steps/s; DQN's at 2 steps/s
    ppo_rate = sorted([budget[ppo0] / 100.0, budget[ppo1] / 2 / 40.0])
    assert table.loc[ppo1, "left_s"] == pytest.approx((budget[ppo1] - budget[ppo1] // 2) / (sum(ppo_rate) / 2))
    assert table.loc["env_1__dqn__1__bench", "left_s"] == pytest.approx(budget["env_1__dqn__1__bench"] / 2.0)

    assert main(["benchmark", "--status", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "1 finished, 1 training, 1 stopped, 1 pending" in printed
    assert printed.startswith("preset smoke, task version 3, commit aaaaaaa (2 trials) and bbbbbbb (1 trial)")
    assert main(["benchmark", "--status", "--out", str(tmp_path / "none")]) == 2
    assert "no benchmark.json" in capsys.readouterr().err
    started = out / "trials" / "env_1__dqn__1__bench" / "env_1__dqn__1__20261126-0900"
    started.mkdir(parents=True)  # before its first checkpoint: no state.json yet
    (started / "config.yaml").write_text("algo: dqn\n")
    (started / "run.lock").write_text(f"{os.getpid()}\n")
    assert grid_status(out).set_index("cell").loc["env_1__dqn__1__bench", "state"] == "training"
    (started / "run.lock").write_text("")  # released: it stopped before a checkpoint
    assert grid_status(out).set_index("cell").loc["env_1__dqn__1__bench", "state"] == "stopped"


@needs_ray
def test_a_trial_line_callback_pickled_by_an_older_grid_still_says_its_lines():
    # the grid started at e3acfc2 pickled TrialLines(out, say): restoring it must not fail
    import pickle

    from eval.scale.trial_lines import TrialLines

    said = []
    old = TrialLines.__new__(TrialLines)  # the instance state that version pickled
    old.__dict__.update({"out": Path("/nowhere"), "say": print, "start": {}})
    restored = pickle.loads(pickle.dumps(old))
    restored.say = said.append

    class Trial:
        trial_id, config = "t1", {"cell": {}}

        def __str__(self):
            return "env_1__td3__0__bench"

    restored.on_trial_start(0, [], Trial())
    restored.on_trial_complete(0, [], Trial())
    assert len(said) == 1 and said[0].startswith("trained env_1__td3__0__bench (")
    new = TrialLines(said.append, lambda: (3, 30), lambda cell: "env_2__ppo__0__bench")
    new.on_trial_complete(0, [], Trial())
    assert said[1].startswith("[3/30] trained env_2__ppo__0__bench (")


def test_two_trials_ending_together_are_counted_once_each():
    """Issue 60: the console said "[2/30]" for two trials and no "[1/30]", the second trial's
    checkpoint already on disk when the first one's line was said. A restored grid (the
    callback unpickled) counts on from the folder's count at its setup."""
    pytest.importorskip("ray")
    from eval.scale.trial_lines import TrialLines

    class Trial:
        def __init__(self, tid):
            self.trial_id, self.config = tid, {"cell": {"name": tid}}

    finished, said = [0], []
    lines = TrialLines(said.append, lambda: (finished[0], 30), lambda cell: cell["name"])
    lines.setup()
    for tid in ("a", "b"):
        lines.on_trial_start(0, [], Trial(tid))
    finished[0] = 2  # both checkpoints on disk before the first line
    lines.on_trial_complete(0, [], Trial("a"))
    lines.on_trial_complete(0, [], Trial("b"))
    lines.on_trial_error(0, [], Trial("c"))
    assert [s.split(" (")[0] for s in said] == ["[1/30] trained a", "[2/30] trained b", "[2/30] FAILED c"]
    restored = TrialLines.__new__(TrialLines)  # what unpickling does (the lambdas do not pickle)
    restored.__setstate__(lines.__getstate__())
    assert restored.base is None and not restored.ended
    restored.setup()
    restored.on_trial_complete(0, [], Trial("d"))
    assert said[-1].startswith("[3/30] trained d (")
