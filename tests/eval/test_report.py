"""The paper-ready report of `cosim test` (issue 13): combined Table RQ1, figures,
index with provenance, the AC selection rule, failure replays, determinism."""

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from gymnasium import spaces

from eval.cli import main
from eval.reporting.report import (
    TABLE_METRICS,
    cell,
    provenance,
    row_name,
    sha256,
    write_paper_report,
)
from eval.reporting.stats import bootstrap_ci
from eval.testing import replay, selection
from eval.testing.jobs import run_protocol
from eval.testing.protocol import ProtocolPlan

ARGS = ["test", "--policy", "random", "--agents", "2", "--envs", "env_1", "env_3",
        "--episodes", "2", "--steps", "30", "--quiet", "--references", "none"]
FIGURES = ("rq2_safety", "rq2_efficiency", "rq2_lane_keeping", "speed_per_timestep", "ttfc_survival")
NUMBER = re.compile(r"^-?\d+\.\d+ \[-?\d+\.\d+, -?\d+\.\d+\]( \(n=\d+\))?$")
"""A cell over two or more episodes: the mean and its interval's two ends."""


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    """The same `cosim test` command run twice: the two report folders."""
    folders = []
    for k in range(2):
        out = tmp_path_factory.mktemp(f"run{k}")
        assert main([*ARGS, "--out", str(out)]) == 0
        (folder,) = out.iterdir()
        folders.append(folder)
    return folders


def test_combined_rq1_has_every_cell_and_dash_where_a_metric_does_not_apply(reports):
    folder = reports[0]
    long = pd.read_csv(folder / "rq1_long.csv", keep_default_na=False)
    labels = ["random (ppo slot)", "random (a3c slot)"]
    for s in (1, 2):
        for env in ("env_1", "env_3"):
            for label in labels:
                for m in TABLE_METRICS:
                    (row,) = long[(long.scenario == s) & (long.env == env) & (long.label == label)
                                  & (long.metric == m)].itertuples()
                    if s == 2 and m in ("CV", "CP", "CV_events", "CP_events") or (
                            env == "env_1" and m in ("CP", "CP_events")):
                        assert row.cell == "-", (s, env, label, m)   # no car / no pedestrian
                    elif m == "TTFC" and row.n == 0:
                        assert row.cell == "--"
                    elif row.n == 1:  # a TTFC of one episode in two
                        assert row.cell.endswith(" (n = 1: no interval)"), row.cell
                    else:
                        assert NUMBER.match(row.cell), (s, env, label, m, row.cell)
                        assert float(row.ci_low) <= float(row.mean) <= float(row.ci_high)
                        assert row.episodes == 2
    assert set(long.title) == {"Straight", "Four-way"}
    wide = pd.read_csv(folder / "rq1_wide.csv", keep_default_na=False)
    assert list(wide.columns) == ["Environment", "Metric", *(f"S{s} {lab}" for s in (1, 2) for lab in labels)]
    assert list(wide.Metric[:1 + len(TABLE_METRICS)]) == ["n (episodes)", *map(row_name, TABLE_METRICS)]
    assert list(wide.Metric[1:4]) == ["DS", "RC", "success rate"]  # the driving score first
    md = (folder / "rq1.md").read_text()
    assert md.count("**Straight**") == 1 and md.count("**Four-way**") == 1


def _balanced(tex: str) -> None:
    envs = re.findall(r"\\(begin|end)\{(\w+\*?)\}", tex)
    stack = []
    for kind, name in envs:
        if kind == "begin":
            stack.append(name)
        else:
            assert stack.pop() == name
    assert not stack
    assert tex.count("{") == tex.count("}")
    body = tex.split(r"\midrule", 1)[1].split(r"\bottomrule")[0]
    rows = [r for r in body.split(r"\\") if "&" in r]
    assert len({r.count("&") for r in rows}) == 1 and rows[0].count("&") == 2 + 2 * 2 - 1
    assert all(c.count("$") % 2 == 0 for c in rows)


def test_latex_is_booktabs_multirow_and_compiles_or_is_balanced(reports, tmp_path):
    tex = (reports[0] / "rq1.tex").read_text()
    assert rf"\multirow{{{1 + len(TABLE_METRICS)}}}{{*}}{{Straight}}" in tex and r"\toprule" in tex and r"\cmidrule" in tex
    _balanced(tex)
    engine = shutil.which("pdflatex")
    if engine:
        doc = tmp_path / "t.tex"
        doc.write_text("\\documentclass{article}\\usepackage{booktabs,multirow,graphicx}\\begin{document}\n"
                       + tex + "\\end{document}\n")
        done = subprocess.run([engine, "-interaction=nonstopmode", doc.name], cwd=tmp_path,
                              capture_output=True, timeout=120)
        assert done.returncode == 0, done.stdout[-2000:]


def test_every_figure_as_pdf_and_png_and_the_index_links_every_file(reports):
    folder = reports[0]
    for stem in FIGURES:
        assert (folder / f"{stem}.pdf").read_bytes()[:4] == b"%PDF"
        assert (folder / f"{stem}.png").read_bytes()[:4] == b"\x89PNG"
    html = (folder / "index.html").read_text()
    for path in folder.rglob("*"):
        rel = path.relative_to(folder).as_posix()
        if path.is_file() and path.name not in ("index.html", "index.md", "report.md"):
            assert f'href="{rel}"' in html, rel
    assert "Policy: random" in html and "random (ppo slot)" in html
    prov = json.loads((folder / "provenance.json").read_text())
    assert prov["policy"] == "random" and prov["plan"]["episode_seeds"] == [0, 1]
    assert prov["command"].startswith("cosim test --agents 2 --envs env_1 env_3")


def test_same_command_twice_gives_identical_records_and_tables(reports):
    a, b = reports
    pd.testing.assert_frame_equal(pd.read_parquet(a / "records.parquet"),
                                  pd.read_parquet(b / "records.parquet"))
    for name in ("rq1.md", "rq1.tex", "rq1_long.csv", "rq1_wide.csv", "episodes.csv", "metrics.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_bootstrap_is_deterministic_and_cells_say_when_nothing_applies():
    assert bootstrap_ci([1.0, 2.0, 3.0]) == bootstrap_ci([1.0, 2.0, 3.0])
    mean, lo, hi, n = bootstrap_ci([1.0, np.nan, 3.0])
    assert (mean, n) == (2.0, 2) and 1.0 <= lo <= mean <= hi <= 3.0
    assert cell("CV", *bootstrap_ci([np.nan]), 1) == "-"
    assert cell("TTFC", *bootstrap_ci([]), 2) == "--"
    assert cell("TTFC", 1.5, 1.5, 1.5, 1, 2) == "1.50 (n = 1: no interval)"
    assert cell("CO", 0.306, 0.0, 0.916, 3, 3) == "0.306 [0.000, 0.916]"  # asymmetric: both ends
    assert cell("CO", 0.25, 0.25, 0.25, 1, 1) == "0.250"  # one episode: its value, no interval


_SAVED: dict[str, Path] = {}


def _run(root: Path, algo: str, best: dict | None, returns: dict | None) -> Path:
    from agents.registry import get_agent_class

    run = root / f"env_1__{algo}__0__20260101-000000"
    obs = spaces.Box(0, 255, (84, 84, 3), np.uint8)
    if algo not in _SAVED:  # one smoke agent per algorithm, copied (making one is slow)
        _SAVED[algo] = root.parent / f"{algo}.pt"
        get_agent_class(algo).from_spaces(obs, spaces.Discrete(9)).save(_SAVED[algo])
    for ac in ("ac_0", "ac_1", "ac_2"):
        (run / "checkpoints" / ac).mkdir(parents=True)
        shutil.copy(_SAVED[algo], run / "checkpoints" / ac / "best.pt")
    if best is not None:
        (run / "state.json").write_text(json.dumps({"best": best}))
    if returns is not None:
        pd.DataFrame([{"agent": a, "return": r} for a, rs in returns.items() for r in rs]).to_csv(
            run / "episodes.csv", index=False)
    return run


def test_the_ac_that_trained_best_represents_the_run(tmp_path):
    run = _run(tmp_path / "a", "ppo", {"ac_0": -5.0, "ac_1": 3.0, "ac_2": 1.0}, None)
    chosen = selection.choose(run)
    assert (chosen.ac, chosen.basis, chosen.path.name) == ("ac_1", "state.json best", "best.pt")
    run = _run(tmp_path / "b", "ppo", None, {"ac_0": [1, 1], "ac_1": [0, 0], "ac_2": [-9] * 30 + [5] * 20})
    assert selection.choose(run).ac == "ac_2"  # the last 20 episodes count
    run = _run(tmp_path / "c", "ppo", None, None)
    assert selection.choose(run).ac == "ac_0"


def test_report_names_the_checkpoints_tested_with_hashes(tmp_path):
    _SAVED.clear()
    run = _run(tmp_path / "runs", "ppo", {"ac_0": -5.0, "ac_1": -1.0, "ac_2": -3.0}, None)
    out = tmp_path / "out"
    given = ["--checkpoint", f"a3c={_run(tmp_path / 'a3c', 'a3c', None, None)}/checkpoints/ac_2/best.pt"]
    assert main(["test", "--agents", "2", "--runs", str(tmp_path / "runs"), *given, "--envs", "env_1",
                 "--scenario", "2", "--episodes", "1", "--steps", "5", "--quiet", "--references",
                 "none", "--no-replays", "--out", str(out)]) == 0
    (folder,) = out.iterdir()
    html = (folder / "index.html").read_text()
    ckpt = run / "checkpoints" / "ac_1" / "best.pt"
    assert str(ckpt) in html and sha256(ckpt) in html and "state.json best" in html
    assert "given (--checkpoint)" in html and "Policy:" not in html
    prov = json.loads((folder / "provenance.json").read_text())
    assert [t["label"] for t in prov["tested"]] == ["ppo", "a3c"]
    assert [t["ac"] for t in prov["tested"]] == ["ac_1", "ac_2"]
    assert prov["tested"][0]["scores"] == {"ac_0": -5.0, "ac_1": -1.0, "ac_2": -3.0}
    assert "S2 ppo" in (folder / "rq1.md").read_text()


class Rammer:
    """Puts a standing car 14 m ahead of its AC at the first step, then drives into it."""

    def __init__(self, env, agent):
        self.env, self.agent, self.placed = env, agent, False

    def reset(self):
        self.placed = False

    def act(self, obs, deterministic=True):
        if not self.placed:
            x, y, h, _ = self.env.world.ac_state(self.agent)
            self.env.world.bridge.place_car("target", x + 14 * np.cos(h), y + 14 * np.sin(h), h, "st_e")
            self.placed = True
        return np.array([1.0, 0.0], np.float32)


def _car_blue(image) -> float:
    """Share of pixels of the background cars' blue (cosim/mirror.py COLORS["car"]), not sky."""
    im = np.asarray(image)[..., :3].astype(int)
    r, g, b = im[..., 0], im[..., 1], im[..., 2]
    return float(((b > 120) & (b > r + 90) & (b > g + 80)).mean())


def test_failure_replay_of_a_real_collision(tmp_path, capsys):
    plan = ProtocolPlan(envs=("env_1",), scenarios=(1,), episodes=1, steps=30, agents=1)
    make = lambda env, agent, algo: Rammer(env, agent)  # noqa: E731
    records = run_protocol(plan, make, ["ddpg"])
    rows = replay.capture(plan, make, ["ddpg"], records, tmp_path)
    (row,) = rows
    assert row["kind"] == "vehicle" and row["reproduced"] and row["step"] == int(
        records[records.collision].step.min())
    write_paper_report(records, tmp_path, prov=provenance(policy="trained", plan=plan, algos=["ddpg"]),
                       replays=rows)
    html = (tmp_path / "index.html").read_text()
    for key in ("camera", "overview", "strip", "state", "meta"):
        assert f'href="{row[key]}"' in html
    # next to the metric that counts it: a row after TTFC in the index's Table RQ1
    index = (tmp_path / "index.md").read_text()
    assert f"| first collision | [clip]({row['strip']}) [state]({row['meta']}) |" in index
    assert index.index("| TTFC |") < index.index("| first collision |") < index.index("| SPEED |")
    import imageio.v3 as iio

    frames = iio.imread(tmp_path / row["camera"])
    assert 10 <= len(frames) <= replay.BEFORE + replay.AFTER + 1
    # the camera just before the collision: the car ahead (blue) fills much of the picture
    ahead = max(_car_blue(f) for f in frames[max(0, row["frame"] - 3): row["frame"] + 1])
    assert ahead > 0.1
    assert _car_blue(frames[0]) < ahead / 2  # 14 m away at the start
    # the SUMO state reloads to the same positions
    again = replay.reload(tmp_path / row["meta"])
    assert set(again["positions"]["vehicles"]) == set(again["meta"]["positions"]["vehicles"])
    assert "target" in again["positions"]["vehicles"] and again["max_deviation_m"] < 0.05
    assert main(["replay", str(tmp_path / row["meta"]), "--plot", str(tmp_path / "p.png")]) == 0
    assert "<- collided" in capsys.readouterr().out and (tmp_path / "p.png").exists()
    assert main(["replay", str(tmp_path / "records.parquet")]) == 2
    assert "not a failure replay" in capsys.readouterr().err


def test_cross_play_and_a_sweep_on_tiny_budgets(tmp_path):
    assert main(["test", "--policy", "autopilot", "--agents", "2", "--envs", "env_1", "--scenario", "1",
                 "--episodes", "1", "--steps", "15", "--quiet", "--references", "none", "--no-replays",
                 "--cross-play", "--cross-play-group", "2", "--sweep", "density=0.5,2",
                 "--out", str(tmp_path)]) == 0
    (folder,) = tmp_path.iterdir()
    cross = pd.read_csv(folder / "crossplay.csv")
    pooled = cross[cross.env == "all"]
    assert sorted(zip(pooled.ego, pooled.partner, strict=True)) == sorted(
        (e, p) for e in ("ppo", "a3c") for p in ("ppo", "a3c", "autopilot"))
    assert pooled.collision_rate.between(0, 1).all() and (pooled.n == 1).all()
    sweep = pd.read_csv(folder / "sweep_density.csv")
    assert sorted(sweep.level.unique()) == [0.5, 2.0] and set(sweep.algorithm) == {"ppo", "a3c"}
    html = (folder / "index.html").read_text()
    for stem in ("crossplay_heatmap", "sweep_density"):
        assert (folder / f"{stem}.pdf").exists() and f'href="{stem}.png"' in html
    assert "autopilot (ppo slot)" in (folder / "crossplay.md").read_text()


def test_sweep_levels_are_checked_and_perturbations_are_seeded():
    from eval.testing.protocol import ProtocolError
    from eval.testing.robustness import Perturbed, parse_sweeps

    assert parse_sweeps(["density=0.5,1,2", "dropout=0,0.3"]) == {"density": [0.5, 1.0, 2.0],
                                                                  "dropout": [0.0, 0.3]}
    for bad in ("speed=1", "density", "dropout=2", "camera_noise=a"):
        with pytest.raises(ProtocolError, match="--sweep"):
            parse_sweeps([bad])
    seen = []
    policy = lambda obs: (seen.append(obs.copy()), 0)[1]  # noqa: E731
    frames = [np.full((4, 4, 3), k, np.uint8) for k in range(20)]
    for kind, level in (("camera_noise", 0.1), ("dropout", 0.5)):
        runs = []
        for _ in range(2):
            seen.clear()
            p = Perturbed(policy, spaces.Discrete(9), kind, level, seed=3)
            for f in frames:
                p.act(f)
            runs.append([s.copy() for s in seen])
        assert all((a == b).all() for a, b in zip(*runs, strict=True))  # seeded
        if kind == "camera_noise":
            assert not (runs[0][5] == frames[5]).all()
        else:  # some frames lost: the policy saw an earlier frame again
            assert any((s == frames[k - 1]).all() for k, s in enumerate(runs[0]) if k)


def test_provenance_and_a_run_manifest_record_what_ran_alike():
    """One builder (eval.training.runfolder.software) for the command, Python, platform, versions and git
    commit of a report's provenance.json and a run's manifest.json."""
    from eval.training import runfolder
    from eval.training.config import TrainConfig

    prov = provenance(policy="autopilot", plan=ProtocolPlan(envs=("env_1",)), algos=["ppo"],
                      command=["test", "--agents", "1"])
    manifest = runfolder.manifest(TrainConfig(algo="ppo", agents=1))
    ran = set(runfolder.software())
    assert ran == {"command", "task_version", "python", "platform", "cpu", "versions", "git", "git_at_start"}
    assert ran <= set(prov) and ran <= set(manifest)
    import cosim

    assert prov["task_version"] == manifest["task_version"] == cosim.TASK_VERSION == 5
    assert prov["command"] == "cosim test --agents 1"
    assert prov["cosim_version"] == prov["versions"]["cosim"]
    assert set(prov["versions"]) == set(manifest["versions"]) == set(runfolder.PACKAGES)
    git = runfolder.git_commit()
    assert git is None or (set(git) == {"commit", "dirty"} and isinstance(git["dirty"], bool))


def test_the_cpu_model_comes_from_cpuinfo_else_the_platform(tmp_path, monkeypatch):
    """A run's manifest names its CPU: torch's float results differ between CPUs (docs/design.md)."""
    from eval.training import runfolder

    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: Intel(R) Xeon(R) Platinum 8480C\n"
                    "processor\t: 1\nmodel name\t: Intel(R) Xeon(R) Platinum 8480C\n")
    assert runfolder.cpu_model(info) == "Intel(R) Xeon(R) Platinum 8480C"
    monkeypatch.setattr(runfolder.platform, "processor", lambda: "arm")
    assert runfolder.cpu_model(tmp_path / "absent") == "arm"
    info.write_text("processor\t: 0\nmodel name\t:\n")
    monkeypatch.setattr(runfolder.platform, "processor", lambda: "")
    assert runfolder.cpu_model(info) is None
    assert runfolder.software()["cpu"] == runfolder.cpu_model()


def test_provenance_names_the_code_that_ran_when_the_checkout_moved_on(monkeypatch):
    """A process started at one commit and writing provenance after a later one says both."""
    from eval.reporting.page import provenance_markdown
    from eval.training import runfolder

    monkeypatch.setattr(runfolder, "GIT_AT_START", {"commit": "a" * 40, "dirty": False})
    monkeypatch.setattr(runfolder, "git_commit", lambda: {"commit": "b" * 40, "dirty": False})
    prov = runfolder.software()
    assert prov["git_at_start"]["commit"] == "a" * 40 and prov["git"]["commit"] == "b" * 40
    text = "\n".join(provenance_markdown(prov))
    assert "| git commit of the code that ran (at the process's start) | " + "a" * 40 in text
    prov["git_at_start"] = prov["git"]
    assert "code that ran" not in "\n".join(provenance_markdown(prov))
