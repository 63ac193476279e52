"""The report page a reader can trust at a glance (issue 28): its first screen says what was
tested and how much (and a headless Chromium sees it there), intervals that do not mislead,
a legend for every abbreviation, provenance as tables for every environment, the return,
goal-rate and reference rows. Built from synthetic records and run folders: seconds, no
simulation."""

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from eval.reporting import figures, page
from eval.reporting.report import provenance, write_paper_report
from eval.testing.protocol import ProtocolPlan
from eval.testing.validity import POLICIES
from eval.training.runfolder import cpu_model

ENVS = ("env_1", "env_3")
ALGOS = ["ppo", "dqn"]


def synthetic_records(episodes: int, steps: int = 20, seed: int = 0, same_scenarios: bool = False) -> pd.DataFrame:
    """Per-step records shaped like the test protocol's (eval/testing/records.py) for ENVS x
    ALGOS x both scenarios; ``same_scenarios``: Scenario 2 drives exactly as Scenario 1."""
    rng = np.random.default_rng(seed)
    rows = []
    for env in ENVS:
        for ep in range(episodes):
            for k, algo in enumerate(ALGOS):
                hit = int(rng.integers(3, steps)) if rng.random() < 0.6 else None
                drive = [(float(rng.uniform(0, 10)), bool(rng.random() < 0.3), float(rng.normal()))
                         for _ in range(steps)]
                for scenario in (1, 2):
                    if not same_scenarios and scenario == 2:
                        hit = int(rng.integers(3, steps)) if rng.random() < 0.5 else None
                        drive = [(s + rng.uniform(0, 2), off, r - 1) for s, off, r in drive]
                    for t, (speed, off, reward) in enumerate(drive):
                        coll = hit is not None and t >= hit and not same_scenarios
                        rows.append({
                            "episode": ep, "seed": ep, "step": t, "agent": f"ac_{k}", "algorithm": algo,
                            "x": float(t), "y": 0.0, "heading": 0.0, "speed": speed,
                            "distance_to_goal": 100.0 - t, "progress": float(t),
                            "n_vehicles": 3 if scenario == 1 else 0,
                            "n_pedestrians": 2 if scenario == 1 and env == "env_3" else 0,
                            "spawn_x": 0.0, "spawn_y": 0.0, "goal_x": 100.0, "goal_y": 0.0, "time": t * 0.1,
                            "collision": coll, "collision_vehicle": coll and scenario == 1,
                            "collision_object": coll and scenario == 2, "collision_pedestrian": False,
                            "event_vehicle": coll and scenario == 1 and t == hit,
                            "event_object": coll and scenario == 2 and t == hit, "event_pedestrian": False,
                            "route_completion": 1.0 if ep == 1 and t == steps - 1 else t / 100.0,
                            "lane_violation": off, "red_light": False,
                            "goal_reached": ep == 1 and t == steps - 1, "reward": reward,
                            "terminated": False, "truncated": t == steps - 1, "env": env,
                            "scenario": scenario})
    return pd.DataFrame(rows)


def run_folder(root: Path, env: str, algo: str, seed: int = 0) -> Path:
    """A finished smoke run folder as `cosim benchmark` leaves it (config, scores, two ACs)."""
    run = root / f"{env}__{algo}__{seed}__bench"
    for ac in ("ac_0", "ac_1"):
        (run / "checkpoints" / ac).mkdir(parents=True, exist_ok=True)
        (run / "checkpoints" / ac / "best.pt").write_bytes(f"{env} {algo} {seed} {ac}".encode())
    (run / "state.json").write_text(json.dumps({"best": {"ac_0": -5.0, "ac_1": 3.0}}))
    (run / "config.yaml").write_text(
        f"algo: {algo}\nenv: {env}\nagents: 2\nsteps: 120\nseed: {seed}\npreset: smoke\nhorizon: 60\n"
        "obs: image\nimage_size: 84\nframe_stack: 4\ncollisions_end_episode: false\n")
    return run


def synthetic_references() -> pd.DataFrame:
    """The whole reference suite's summary (eval.testing.session.reference_rows) in ENVS."""
    return pd.DataFrame([{"policy": p, "DS": 0.95 - 0.05 * i, "RC": 0.96 - 0.05 * i, "success": 0.5 * (i < 2),
                          "return": 100.0 - 10 * i, "goal": 0.5 * (i < 2), "DISTANCE": 10.0,
                          "CV": 0.0, "CO": 0.1 * (i % 3), "CP": np.nan if env == "env_1" else 0.0,
                          "OS": 0.2, "RL": 0.0, "collision_steps": 0.0, "TTFC": np.nan, "SPEED": 20.0,
                          "n": 4, "env": env}
                         for env in ENVS for i, p in enumerate(POLICIES)])


def benchmark_report(out: Path, episodes: int = 1, records: pd.DataFrame | None = None,
                     figures_too: bool = False) -> tuple[Path, list[dict]]:
    """A smoke benchmark's report (eval.scale.benchmark.write_report's provenance) of
    synthetic records: its folder and the checkpoints it names."""
    tested = [{"env": e, "seed": 0, "algorithm": a,
               "path": run_folder(out / "runs", e, a) / "checkpoints" / "ac_1" / "best.pt"}
              for e in ENVS for a in ALGOS]
    plan = ProtocolPlan(envs=ENVS, episodes=episodes, steps=20, seed=10_000, agents=len(ALGOS))
    bench = {"preset": "smoke", "envs": list(ENVS), "algos": ALGOS, "seeds": 1, "steps": None,
             "collisions": "event"}
    prov = provenance(policy="trained", plan=plan, algos=ALGOS,
                      checkpoints={t["algorithm"]: t["path"] for t in tested if t["env"] == ENVS[0]},
                      command=["benchmark", "--preset", "smoke"], env_checkpoints=tested, benchmark=bench)
    records = synthetic_records(episodes) if records is None else records
    write_paper_report(records, out / "report", prov=prov, references=synthetic_references(),
                       figures=figures_too)
    return out / "report", tested


@pytest.fixture(scope="module")
def one_episode(tmp_path_factory):
    return benchmark_report(tmp_path_factory.mktemp("one"), episodes=1)


@pytest.fixture(scope="module")
def three_episodes(tmp_path_factory):
    return benchmark_report(tmp_path_factory.mktemp("three"), episodes=3)


def _section(md: str, heading: str) -> str:
    """The Markdown between ``heading`` and the next heading of any level."""
    start = md.index(heading) + len(heading)
    nxt = re.search(r"^#", md[start:], re.M)
    return md[start:start + nxt.start()] if nxt else md[start:]


def test_the_first_screen_says_what_was_tested_and_how_much(one_episode):
    folder, _ = one_episode
    md = (folder / "index.md").read_text()
    first = md[:md.index("## Table RQ1")]
    prov = json.loads((folder / "provenance.json").read_text())
    assert md.startswith("# cosim benchmark report (preset smoke)\n")  # what produced it
    for fact in ("`cosim benchmark --preset smoke`", "smoke", "ppo 120 env steps x 2 ACs",
                 "1 episode(s) x 20 steps", "episode seeds 10000", "Straight (env_1)",
                 prov["task"]["env_1"]["sha256"], "image 84px x 4 frames", "Discrete(9): ppo, dqn",
                 prov["date"]):
        assert fact in first, fact
    if prov["git"]:
        assert prov["git"]["commit"][:10] in first
    assert "| setting | value |" in first  # a small table, not a dict
    html = (folder / "index.html").read_text()
    assert "<title>cosim benchmark report (preset smoke)</title>" in html


def test_a_test_report_is_titled_as_one(tmp_path):
    plan = ProtocolPlan(envs=ENVS, episodes=1, steps=20, agents=2)
    prov = provenance(policy="random", plan=plan, algos=ALGOS, command=["test", "--policy", "random"])
    write_paper_report(synthetic_records(1), tmp_path, prov=prov, figures=False)
    md = (tmp_path / "index.md").read_text()
    assert md.startswith("# cosim test report\n") and "random reference policy" in md
    assert "No checkpoint: every AC was driven by the random policy." in md


def test_one_episode_prints_no_zero_interval(one_episode):
    folder, _ = one_episode
    for name in ("index.html", "index.md", "rq1.md", "rq1_wide.csv", "rq1.tex"):
        text = (folder / name).read_text()
        assert "± 0.0" not in text and "\\pm" not in text, name
    assert "n = 1: no interval" in (folder / "index.html").read_text()


def test_an_asymmetric_interval_prints_its_two_ends(three_episodes):
    folder, _ = three_episodes
    long = pd.read_csv(folder / "rq1_long.csv")
    rows = long[(long.n > 1) & ((long.ci_high - long["mean"]) - (long["mean"] - long.ci_low)).abs().gt(1e-3)]
    assert len(rows) > 0
    html = (folder / "index.html").read_text()
    assert "±" not in html
    for r in rows.itertuples():
        d = 3 if r.metric in ("CV", "CO", "CP", "OS", "RL") else None
        if d:
            assert f"{r.mean:.3f} [{r.ci_low:.3f}, {r.ci_high:.3f}]" in r.cell
            assert r.cell in html


NOT_METRICS = {"SUMO", "SHA", "UTC", "PDF", "PNG", "CSV", "HTML", "XML", "YAML", "RQ1", "RQ2", "RGB",
               "NO", "PPO", "DQN", "A3C", "DDPG", "TD3", "IMPALA", "CPU", "GPU"}
"""Upper-case words that are names (tools, formats, algorithms), not metric abbreviations."""


def test_the_first_screen_opens_with_the_driving_score(three_episodes):
    """Before Table RQ1, a table of DS, RC and success rate [95% CI] per environment, scenario and
    column (then the reference columns); Table RQ1's first rows after n are DS, RC, success rate."""
    folder, _ = three_episodes
    md = (folder / "index.md").read_text()
    assert md.index("## Driving score") < md.index("## Table RQ1") < md.index("### Legend")
    table = [line for line in _section(md, "## Driving score").splitlines() if line.startswith("| ")]
    assert table[0] == "| environment | scenario | policy | DS | RC | success rate | n |"
    long = pd.read_csv(folder / "rq1_long.csv", keep_default_na=False).set_index(
        ["env", "scenario", "algorithm", "metric"])["cell"]
    assert (f"| Straight | S1 | ppo | {long[('env_1', 1, 'ppo', 'DS')]} | {long[('env_1', 1, 'ppo', 'RC')]} | "
            f"{long[('env_1', 1, 'ppo', 'success')]} | 3 |") in table
    assert re.match(r"^\d\.\d{3} \[\d\.\d{3}, \d\.\d{3}\]$", long[("env_1", 1, "ppo", "DS")])
    assert "| Four-way | S1 | autopilot (ref) | 0.950 | 0.960 | 0.50 | 4 AC-episodes |" in table
    assert "| Four-way | S2 | dqn |" in "\n".join(table)
    wide = pd.read_csv(folder / "rq1_wide.csv", keep_default_na=False)
    for env in ("Straight", "Four-way"):
        assert wide[wide.Environment == env].Metric.tolist()[:4] == ["n (episodes)", "DS", "RC", "success rate"]
    html = (folder / "index.html").read_text()
    assert html.index("<h2>Driving score</h2>") < html.index("<h2>Table RQ1</h2>")


def test_every_abbreviation_on_the_page_has_its_definition(one_episode):
    folder, _ = one_episode
    md = (folder / "index.md").read_text()
    legend = {line.split("|")[1].strip() for line in _section(md, "### Legend").splitlines()
              if line.startswith("| ") and not line.startswith("| term")}
    assert {"CV", "CO", "CP", "OS", "RL", "TTFC", "SPEED", "DISTANCE", "return", "goal rate",
            "S1", "S2", "AC", "CI", "n", "(ref)", "-", "--"} <= legend
    rq1 = _section(md, "## Table RQ1")
    metrics = {line.split("|")[2].strip() for line in rq1.splitlines() if line.startswith("| ")}
    assert metrics - {"Metric", "---", "n (episodes)"} <= legend
    text = re.sub(r"<[^>]+>", " ", (folder / "index.html").read_text())
    text = re.sub(r"\S*[/_.]\S*", " ", text)  # paths, file names and hashes are not words
    words = set(re.findall(r"\b[A-Z][A-Z0-9]{1,5}\b", text))
    machine = set(re.findall(r"\b[A-Z][A-Z0-9]{1,5}\b", cpu_model() or ""))  # "AMD EPYC": a name
    assert words - NOT_METRICS - machine <= legend, words - NOT_METRICS - machine - legend


def test_provenance_has_every_environments_checkpoints_as_tables(one_episode):
    folder, tested = one_episode
    html = (folder / "index.html").read_text()
    prov = json.loads((folder / "provenance.json").read_text())
    assert len(prov["checkpoints"]) == len(ENVS) * len(ALGOS)
    table = html[html.index("<h3>Checkpoints</h3>"):]
    table = table[:table.index("</table>")]
    for t in tested:
        row = next(r for r in table.split("<tr>") if str(t["path"]) in r)
        assert prov["checkpoints"][0]["sha256"] in table
        title = {"env_1": "Straight", "env_3": "Four-way"}[t["env"]]
        assert f"<td>{title}</td>" in row and "<td>ac_1</td>" in row and "state.json best" in row
        assert "ac_0 -5.0, ac_1 3.0" in row and f"{title} (smoke, 120 steps, 2 ACs, seed 0)" in row
    assert "{'" not in html and "': " not in html  # no Python dict anywhere
    for heading in ("What ran", "Benchmark plan", "Test plan", "Task version"):
        assert "<table>" in html.split(f"<h3>{heading}</h3>")[1].split("<h")[0], heading
    if prov["git"]:
        assert f"<td>{prov['git']['commit']}</td>" in html


def test_return_goal_and_reference_rows_beside_the_algorithms(one_episode):
    folder, _ = one_episode
    wide = pd.read_csv(folder / "rq1_wide.csv", keep_default_na=False)
    for name in ("autopilot", "autopilot-discrete", "safe-non-turner", "random", "best degenerate"):
        assert f"S1 {name} (ref)" in wide.columns, name
    s1 = [c for c in wide.columns if c.startswith("S1 ")]
    assert s1[:2] == ["S1 ppo", "S1 dqn"] and not any("(ref)" in c for c in wide.columns if c.startswith("S2"))
    assert set(wide.Environment) == {"Straight", "Four-way"}  # the same names everywhere
    for env in ("Straight", "Four-way"):
        block = wide[wide.Environment == env].set_index("Metric")
        assert {"return", "goal rate"} <= set(block.index)
        assert block.loc["return", "S1 autopilot (ref)"] == "100.0"
        assert block.loc["goal rate", "S1 autopilot-discrete (ref)"] == "0.50"
        assert block.loc["n (episodes)", "S1 best degenerate (ref)"].startswith("random-box, 4 AC-episodes")
        assert block.loc["return", "S1 ppo"] not in ("", "-")
    md = (folder / "index.md").read_text()
    assert "### Straight (env_1)" in md and "### Four-way (env_3)" in md and "### env_1" not in md
    assert r"\multicolumn{7}{c}{Scenario 1" in (folder / "rq1.tex").read_text()


def test_identical_scenario_columns_are_explained(tmp_path):
    folder, _ = benchmark_report(tmp_path, episodes=1, records=synthetic_records(1, same_scenarios=True))
    md = (folder / "index.md").read_text()
    assert "**Identical Scenario 1 and 2 columns** (ppo and dqn" in md
    folder, _ = benchmark_report(tmp_path / "b", episodes=1)
    assert "Identical Scenario 1 and 2" not in (folder / "index.md").read_text()


def test_a_replay_not_reproduced_says_why():
    row = {"scenario": 1, "title": "Straight", "label": "a3c", "episode": 0, "step": 12, "ttfc": 1.2,
           "kind": "vehicle", "strip": "s.png", "camera": "c.gif", "overview": "o.gif", "state": "s.xml",
           "meta": "s.json", "reproduced": False, "why": "the re-run had no collision at step 12"}
    md = "\n".join(page.replays_markdown([row, {**row, "reproduced": True, "why": ""}]))
    assert "| NO: the re-run had no collision at step 12 |" in md and md.count("| yes |") == 1


def test_zero_bars_are_labelled_and_missing_ones_too(monkeypatch, tmp_path):
    marks = []
    monkeypatch.setattr(figures, "_mark", lambda ax, x, top, text, *a: marks.append(text))
    long = pd.DataFrame([
        {"scenario": 1, "env": "env_1", "title": "Straight", "algorithm": "ppo", "metric": "safety",
         "mean": 0.0, "ci_low": 0.0, "ci_high": 0.0, "n": 1},
        {"scenario": 1, "env": "env_1", "title": "Straight", "algorithm": "dqn", "metric": "safety",
         "mean": 1.0, "ci_low": 1.0, "ci_high": 1.0, "n": 1},
        {"scenario": 1, "env": "env_1", "title": "Straight", "algorithm": "td3", "metric": "safety",
         "mean": np.nan, "ci_low": np.nan, "ci_high": np.nan, "n": 0}])
    figures.bar_figure(long, [("safety", "Safety")], tmp_path, "s", {}, ylim01=True)
    assert sorted(marks) == ["0", "n/a"]


def chromium() -> str | None:
    """Debian's headless Chromium (package ``chromium``), or another install of it."""
    return next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)


FIRST_SCREEN_JS = """<script>
window.addEventListener('load', function () {
  var seen = [];
  document.querySelectorAll('h1,h2,h3,p,li,th,td').forEach(function (el) {
    var r = el.getBoundingClientRect();
    if (r.bottom > 0 && r.top < window.innerHeight && r.width > 0) seen.push(el.innerText);
  });
  var pre = document.createElement('pre');
  pre.id = 'first-screen';
  pre.textContent = seen.join('\\n');
  document.body.appendChild(pre);
});
</script>"""
"""Writes the text of every element inside the first screen (the viewport) into the page."""


def first_screen_text(html_file: Path, browser: str, size: str = "1280,800") -> str:
    """The text a reader sees without scrolling, as headless Chromium lays the page out."""
    probe = html_file.with_name("first_screen_probe.html")
    probe.write_text(html_file.read_text().replace("</body>", FIRST_SCREEN_JS + "</body>"))
    try:
        done = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", f"--window-size={size}",
                               "--dump-dom", probe.resolve().as_uri()], capture_output=True, text=True,
                              timeout=120)
    finally:
        probe.unlink()
    found = re.search(r'<pre id="first-screen">(.*?)</pre>', done.stdout, re.S)
    assert found, done.stderr[-2000:]
    import html

    return html.unescape(found.group(1))


def test_chromium_shows_the_preset_the_budget_and_the_commit_on_the_first_screen(one_episode):
    browser = chromium()
    if browser is None:
        pytest.skip("no chromium binary (Debian: apt-get install chromium): the page's first "
                    "screen is not rendered")
    folder, _ = one_episode
    seen = first_screen_text(folder / "index.html", browser)
    prov = json.loads((folder / "provenance.json").read_text())
    assert "cosim benchmark report (preset smoke)" in seen
    assert "preset" in seen and "smoke" in seen
    assert "ppo 120 env steps x 2 ACs; dqn 120 env steps x 2 ACs" in seen  # the budget
    assert "1 episode(s) x 20 steps" in seen
    commit = (prov["git"] or {}).get("commit")
    assert commit is None or commit[:10] in seen
    assert "Files" not in seen.splitlines()  # the first screen only, not the whole page


def test_the_budget_rows_say_when_actions_were_held(tmp_path):
    """A run trained with action_repeat 2 (config.yaml's agent_config) is reported as such."""
    import yaml

    from eval.reporting.page import budget_rows
    from eval.reporting.report import trained_with

    run = tmp_path / "env_1__ppo__0__20260101-000000"
    run.mkdir()
    (run / "config.yaml").write_text(yaml.safe_dump({"algo": "ppo", "steps": 100, "frame_stack": 4,
                                                     "agent_config": {"action_repeat": 2}}))
    held = trained_with(run)
    assert held["action_repeat"] == 2 and held["steps"] == 100
    plain = {**held, "action_repeat": 1}
    prov = {"checkpoints": [{"algorithm": "ppo", "trained": held}, {"algorithm": "dqn", "trained": plain}]}
    rows = {r[0]: r for r in budget_rows(prov, ["ppo", "dqn"], {})}
    assert rows["ppo"][-1] == "Discrete(9), each held 2 steps" and rows["dqn"][-1] == "Discrete(9)"


def test_the_page_opens_with_who_drives_best_where(tmp_path):
    """Issue 60: above the settings and the tables, the driving-score heat map (algorithms and
    references x environments) and one sentence per environment naming the best algorithm, how
    many clear every degenerate reference by their interval's lower end, and the safe non-turner."""
    from eval.reporting.figures import driving_score_matrix

    folder, _ = benchmark_report(tmp_path, episodes=3, figures_too=True)
    md = (folder / "index.md").read_text()
    assert md.index("## Who drives best where") < md.index("**What was tested.**") < md.index("## Table RQ1")
    assert "![ds_heatmap](ds_heatmap.png)" in md and (folder / "ds_heatmap.png").stat().st_size > 0
    assert md.count("![ds_heatmap]") == 1  # not again among the figures
    long = pd.read_csv(folder / "rq1_long.csv")
    table = driving_score_matrix(long, synthetic_references(), {})
    refs = synthetic_references()
    for env, title in (("env_1", "Straight"), ("env_3", "Four-way")):
        ds = long[(long.env == env) & (long.scenario == 1) & (long.metric == "DS")].set_index("algorithm")
        best = max(ALGOS, key=lambda a: (ds.loc[a, "mean"], -ALGOS.index(a)))  # a tie: the paper's order
        sentence = next(line for line in _section(md, "## Who drives best where").splitlines()
                        if line.startswith(f"**{title}**"))
        assert sentence.startswith(f"**{title}**: {best} drives best, DS {ds.loc[best, 'mean']:.2f} "
                                   f"[{ds.loc[best, 'ci_low']:.2f}, {ds.loc[best, 'ci_high']:.2f}]")
        here = refs[refs.env == env].set_index("policy")["DS"]
        degenerate = here.drop(["autopilot", "autopilot-discrete", "safe-non-turner"]).max()
        clearing = sorted(a for a in ds.index if ds.loc[a, "ci_low"] > degenerate)
        assert f"{len(clearing)} of 2 clear every degenerate reference (the strongest {degenerate:.2f})" in sentence
        assert f"the safe non-turner {here['safe-non-turner']:.2f}" in sentence
        mine = table[(table.env == env) & ~table.reference].set_index("row")
        assert sorted(mine.index[mine["clears"] == True]) == clearing  # noqa: E712
    assert {"autopilot (ref)", "safe-non-turner (ref)", "random (ref)", "best degenerate (ref)"} <= set(table.row)


FIRST_SCREEN_IMAGES_JS = """<script>
window.addEventListener('load', function () {
  var seen = [];
  document.querySelectorAll('img').forEach(function (el) {
    var r = el.getBoundingClientRect();
    if (r.bottom > 0 && r.top < window.innerHeight && r.width > 100 && el.naturalWidth > 0) {
      seen.push(el.getAttribute('src'));
    }
  });
  var pre = document.createElement('pre');
  pre.id = 'first-screen';
  pre.textContent = seen.join('\\n');
  document.body.appendChild(pre);
});
</script>"""
"""Writes the src of every image drawn (loaded, > 100 px wide) inside the first screen."""


def test_chromium_shows_who_drives_best_where_on_a_real_benchmarks_first_screen(tmp_path, monkeypatch):
    """A real `cosim benchmark` (smoke, one junction, DQN and TD3): its report's first screen, as
    headless Chromium lays it out at 1280x800, shows the driving-score heat map and the one-line
    verdict of the environment, above the settings table."""
    browser = chromium()
    if browser is None:
        pytest.skip("no chromium binary (Debian: apt-get install chromium; .ci/run installs it)")
    from eval.cli import main

    out = tmp_path / "b"
    assert main(["benchmark", "--preset", "smoke", "--envs", "env_2", "--algos", "dqn", "td3", "--steps", "20",
                 "--no-ray", "--out", str(out), "--quiet"]) == 0
    page = out / "report" / "index.html"
    seen = first_screen_text(page, browser)
    lines = seen.splitlines()
    assert "Who drives best where" in lines
    verdict = next(line for line in lines if line.startswith("Three-way:"))
    assert re.search(r"^Three-way: (dqn|td3) drives best, DS \d\.\d\d \[", verdict), verdict
    assert "clear every degenerate reference" in verdict and "the safe non-turner" in verdict
    assert lines[:2] == ["cosim benchmark report (preset smoke)", "Who drives best where"]  # above the rest
    probe = page.with_name("first_screen_probe.html")
    probe.write_text(page.read_text().replace("</body>", FIRST_SCREEN_IMAGES_JS + "</body>"))
    done = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--window-size=1280,800",
                           "--dump-dom", probe.resolve().as_uri()], capture_output=True, text=True, timeout=120)
    images = re.search(r'<pre id="first-screen">(.*?)</pre>', done.stdout, re.S)
    assert images and "ds_heatmap.png" in images.group(1).split(), done.stdout[-500:]
