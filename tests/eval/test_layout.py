"""The architecture, checked by what matters: the import direction between the packages (and
agents never touching the simulators), no import cycle, a complexity limit (ruff's C901), and
the facts that have one source (the algorithm catalogue, the environments' scenario files, the
CSV columns, the presets)."""

import ast
import csv
import math
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

import eval
from agents import registry
from cosim.env import EPISODE_EVENTS
from cosim.events import REWARD_TERMS
from eval import labels
from eval.testing import protocol
from eval.training import config, presets, runlog

ROOT = Path(eval.__file__).resolve().parents[1]
PACKAGES = ("cosim", "agents", "eval")
MAY_IMPORT = {"cosim": set(), "agents": set(), "eval": {"cosim", "agents"}}
"""Which project packages each package may import: cosim (simulation) and agents (learning) sit
side by side and import neither each other nor eval; eval, on top, imports both
(docs/design.md#import-direction-and-no-cycles)."""
EVAL_LAYERS = ("eval.cli", "eval.scale", "eval.reporting", "eval.training", "eval.testing", "eval.labels")
"""eval by responsibility, top down: each subpackage imports only those below it (the command
line; Ray, benchmark and PBT; the report; training, whose validation runs test episodes; the
test; the names and colours all of them show). docs/design.md#module-map."""
MAY_NOT_IMPORT = {"agents": {"libsumo", "traci", "sumolib", "pybullet", "pybullet_data"}}
"""Third-party packages a project package must not import: agents learns from Gymnasium spaces
and arrays, never from the simulators."""


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def _imports(name: str, path: Path) -> list[tuple[str, int]]:
    """Every module ``path`` imports, with its line: module level, inside functions, under
    ``if TYPE_CHECKING`` alike (a lazy import is still a dependency); relative imports resolved.
    ``from pkg import mod`` counts as an import of the module ``pkg.mod``."""
    tree = ast.parse(path.read_text(), str(path))
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
            for alias in node.names:
                full = f"{base}.{alias.name}"
                found.append((full if full in MODULES else base, node.lineno))
    return found


def _project_module(target: str) -> str | None:
    """The project module an import names (``eval.reporting.report.bootstrap_ci`` -> ``eval.reporting.report``)."""
    parts = target.split(".")
    while parts and ".".join(parts) not in MODULES:
        parts.pop()
    return ".".join(parts) or None


def _import_graph() -> dict[str, set[str]]:
    return {name: {m for t, _ in _imports(name, path) if (m := _project_module(t)) not in (None, name)}
            for name, path in MODULES.items()}


def test_the_import_graph_sees_every_package_and_lazy_imports(tmp_path):
    assert {m.split(".")[0] for m in MODULES} == set(PACKAGES) and len(MODULES) > 60
    graph = _import_graph()
    assert "eval.cli.learn" in graph["eval.cli"]  # module level
    assert "agents.errors" in graph["eval.cli"]  # inside main(): a function-level import
    probe = tmp_path / "probe.py"  # read as if it were eval/testing/probe.py
    probe.write_text("def f():\n    from ..reporting.report import bootstrap_ci\n    import cosim.errors\n"
                     "    from .. import labels\n    from . import metrics\n")
    assert {t for t, _ in _imports("eval.testing.probe", probe)} == {
        "eval.reporting.report", "cosim.errors", "eval.labels", "eval.testing.metrics"}


def test_cosim_and_agents_never_import_each_other_or_eval():
    wrong = []
    for name, path in MODULES.items():
        package = name.split(".")[0]
        for target, line in _imports(name, path):
            other = target.split(".")[0]
            if (other in PACKAGES and other != package and other not in MAY_IMPORT[package]) or \
                    other in MAY_NOT_IMPORT.get(package, ()):
                wrong.append(f"{path.relative_to(ROOT)}:{line} imports {target}")
    assert not wrong, "import direction (docs/design.md#import-direction-and-no-cycles):\n" + "\n".join(wrong)


def _layer(module: str) -> str | None:
    return next((layer for layer in EVAL_LAYERS if module == layer or module.startswith(layer + ".")), None)


def test_every_eval_module_sits_in_a_subpackage_with_a_one_line_charter():
    stray = [m for m in MODULES if m.startswith("eval.") and _layer(m) is None]
    assert not stray, f"eval modules outside the subpackages {EVAL_LAYERS}: {stray}"
    packages = [layer for layer in EVAL_LAYERS if MODULES[layer].name == "__init__.py"]
    assert len(packages) == 5  # all but labels.py
    for layer in packages:
        path = MODULES[layer]
        doc = ast.get_docstring(ast.parse(path.read_text()), clean=False) or ""
        charter = doc.split("\n")[0]
        assert charter.endswith(".") and len(charter.split()) >= 5, f"{path.relative_to(ROOT)}: {charter!r}"
        if layer != "eval.cli":  # the CLI's docstring goes on with the commands (its --help)
            assert doc.strip() == charter, f"{path.relative_to(ROOT)}: the charter is one line"


def test_evals_subpackages_import_only_those_below_them():
    rank = {layer: i for i, layer in enumerate(EVAL_LAYERS)}
    wrong = []
    for name, path in MODULES.items():
        if not name.startswith("eval."):
            continue
        for target, line in _imports(name, path):
            module = _project_module(target)
            if module and module.startswith("eval.") and rank[_layer(module)] < rank[_layer(name)]:
                wrong.append(f"{path.relative_to(ROOT)}:{line} imports {target}")
    assert not wrong, "eval's layers (docs/design.md#module-map):\n" + "\n".join(wrong)


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles of ``graph`` (module -> the modules it imports): its strongly connected
    components of more than one module (Tarjan), each sorted, in order of their first module.
    Edges to modules outside the graph are ignored."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(cycles)


def test_the_cycle_finder_finds_cycles_in_a_made_up_graph():
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": set(), "d": {"a", "c"}}) == []  # a DAG
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}) == [["a", "b", "c"]]
    # two cycles joined by one edge stay two; a lazy import's edge is an edge like any other
    graph = {"x.cli": {"x.report"}, "x.report": {"x.figures"}, "x.figures": {"x.report", "x.labels"},
             "x.labels": {"x.cli", "numpy"}, "y.a": {"y.b"}, "y.b": {"y.a", "x.cli"}}
    assert find_cycles(graph) == [["x.cli", "x.figures", "x.labels", "x.report"], ["y.a", "y.b"]]
    graph["x.labels"] = {"numpy"}  # break the long cycle: report <-> figures remains
    assert find_cycles(graph) == [["x.figures", "x.report"], ["y.a", "y.b"]]


def test_no_import_cycle_among_the_project_modules():
    cycles = find_cycles(_import_graph())
    assert not cycles, f"import cycles (function-level imports count): {cycles}"


STUDIES = ROOT / "studies"
"""The study scripts: they import the product; the product imports none of them
(docs/design.md#module-map, "The product and the studies")."""


def test_the_product_never_imports_a_study():
    """Neither ``studies.x`` nor a study's bare name (``import science``, as the scripts import
    their siblings with studies/ on ``sys.path``)."""
    scripts = {p.stem for p in STUDIES.glob("*.py")}
    assert {"science", "science_pages"} <= scripts
    wrong = [f"{path.relative_to(ROOT)}:{line} imports {target}" for name, path in MODULES.items()
             for target, line in _imports(name, path)
             if target.split(".")[0] == "studies" or target.split(".")[0] in scripts]
    assert not wrong, "the product imports a study:\n" + "\n".join(wrong)


def _named_imports(name: str, path: Path) -> set[str]:
    """The project modules ``path`` names in a string, imported on first use: a module's name
    (agents/__init__.py's lazy exports: ``"agents.loop"``) or ``"module:attribute"``
    (agents/registry.py's catalogue: ``"agents.ppo:PPO"``)."""
    tree = ast.parse(path.read_text(), str(path))
    return {n.value.split(":")[0] for n in ast.walk(tree) if isinstance(n, ast.Constant)
            and isinstance(n.value, str) and n.value.count(":") <= 1 and n.value.split(":")[0] in MODULES}


def _entry_points() -> set[str]:
    """The modules a user starts from: every package (its ``__init__``), ``__main__`` modules,
    the console scripts of pyproject.toml, and what the examples (users' code) import."""
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    entries = {name for name, path in MODULES.items() if path.name in ("__init__.py", "__main__.py")}
    entries |= {target.split(":")[0] for target in scripts.values()}
    for path in sorted((ROOT / "examples").rglob("*.py")):
        entries |= {m for t, _ in _imports(path.stem, path) if (m := _project_module(t))}
    return entries


def unreached(graph: dict[str, set[str]], entries: set[str]) -> list[str]:
    """The modules of ``graph`` (module -> the modules it imports) that no other module of it
    imports and that are not among ``entries``: code only something outside (a study, a test)
    could be using."""
    imported = {m for source, targets in graph.items() for m in targets if m != source}
    return sorted(m for m in graph if m not in imported and m not in entries)


def test_unreached_finds_a_module_only_something_outside_imports():
    graph = {"p": {"p.cli"}, "p.cli": {"p.report"}, "p.report": {"p.stats"}, "p.stats": set(),
             "p.notebook": {"p.stats"}, "p.self": {"p.self"}}
    assert unreached(graph, {"p", "p.cli"}) == ["p.notebook", "p.self"]  # importing itself is no use
    graph["p.report"].add("p.notebook")
    assert unreached(graph, {"p", "p.cli", "p.self"}) == []


def test_every_product_module_is_imported_by_the_product_or_is_an_entry_point():
    """No module of cosim/, agents/, eval/ is there only for studies/ or the tests: each is
    imported by another product module (a ``"module:attribute"`` string counts), or is an entry
    point (:func:`_entry_points`)."""
    graph = _import_graph()
    for name, path in MODULES.items():
        graph[name] |= _named_imports(name, path) - {name}
    assert "agents.ppo" in graph["agents.registry"] and "agents.loop" in graph["agents"]
    assert "cosim.rllib" in _entry_points()  # examples/rllib_ppo.py
    left = unreached(graph, _entry_points())
    assert not left, ("product modules nothing in the product imports (move a study's to studies/, "
                      f"or import it where it is used): {left}")


def _ruff() -> list[str] | None:
    exe = shutil.which("ruff")
    if exe:
        return [exe]
    try:
        import ruff  # noqa: F401
    except ImportError:
        return None
    return [sys.executable, "-m", "ruff"]


def test_no_function_is_more_complex_than_the_stated_limit():
    """ruff's mccabe rule at pyproject's ``max-complexity`` (docs/design.md#complexity-limit-ruff-c901)."""
    ruff = _ruff()
    if ruff is None:
        pytest.skip("ruff is not installed (pip install -e '.[dev]')")
    lint = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["ruff"]["lint"]
    limit = lint["mccabe"]["max-complexity"]
    assert "C901" in lint["select"] and isinstance(limit, int) and limit <= 17  # never raised
    assert f"`max-complexity = {limit}`" in (ROOT / "docs" / "design.md").read_text()  # the stated limit
    done = subprocess.run([*ruff, "check", "--select", "C901", "--no-cache", "--output-format", "concise", "."],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-1000:]


def test_csv_columns_come_from_the_reward_terms_and_events():
    assert [c for c in runlog.EPISODE_FIELDS if c.startswith("r_")] == [f"r_{t}" for t in REWARD_TERMS]
    assert [c for c in runlog.EPISODE_FIELDS if c.startswith("n_")] == [f"n_{e}" for e in EPISODE_EVENTS]
    # a new term or event gets its column with no edit to the training layer
    fields = runlog.episode_fields((*REWARD_TERMS, "comfort"), (*EPISODE_EVENTS, "honked"))
    assert {"r_comfort", "n_honked"} <= set(fields)
    assert fields[: 5] == runlog.EPISODE_FIELDS[: 5] and fields[-4:] == runlog.EPISODE_FIELDS[-4:]


def test_the_csv_header_written_is_the_derived_columns(tmp_path):
    pytest.importorskip("torch")
    cfg = config.TrainConfig(algo="ppo", agents=1)
    log = runlog.RunLog(tmp_path, cfg, None)
    stats = {c: 1 for c in runlog.EPISODE_FIELDS if c.startswith(("r_", "n_"))}
    log.episode("ac_0", {**stats, "return": 2.0, "length": 3, "mean_speed_kmh": 10.0, "DISTANCE": 4.0,
                         "distance_to_goal": 5.0, "goal_reached": False}, 3)
    log.close()
    with open(tmp_path / "episodes.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == runlog.EPISODE_FIELDS
    assert all(rows[0][c] == "1" for c in stats)


def test_the_algorithm_catalogue_is_the_single_source():
    names = tuple(a.name for a in registry.CATALOGUE)
    assert config.ALGORITHMS == names == tuple(registry.ALGORITHMS)
    assert config.DISCRETE_ALGOS == tuple(a.name for a in registry.CATALOGUE if a.action == "discrete")
    assert config.CONTINUOUS_ALGOS == tuple(a.name for a in registry.CATALOGUE if a.action == "continuous")
    assert config.ASYNC_ALGOS == tuple(a.name for a in registry.CATALOGUE if a.loop == "async")
    assert set(config.DISCRETE_ALGOS) | set(config.CONTINUOUS_ALGOS) == set(names)
    assert (protocol.ALGO_ORDER, protocol.CONTINUOUS) == (names, config.CONTINUOUS_ALGOS)
    for a in registry.CATALOGUE:
        assert a.action in ("discrete", "continuous") and a.loop in ("sync", "async")
        assert registry.get_agent_class(a.name).algo == a.name and registry.get(a.name) is a
        assert (a.loop == "async") == bool(a.async_trainer) and (a.loop == "async" or not a.thread_per_env)
        if a.async_trainer:
            assert callable(registry.get_async_trainer(a.name))
    # the facts eval keeps about each algorithm: every one of the catalogue's, in its order
    assert labels.ALGO_ORDER == names and set(labels.COLOURS) == set(names)
    assert protocol.SAMPLED == registry.STOCHASTIC == tuple(a.name for a in registry.CATALOGUE if a.stochastic)
    assert set(registry.STOCHASTIC) | set(registry.DETERMINISTIC) == set(names)
    assert not set(registry.STOCHASTIC) & set(registry.DETERMINISTIC)
    from eval.scale.pbt import MUTATIONS

    assert set(MUTATIONS) == set(names)


def test_the_environments_are_the_scenario_files():
    """Every "all the environments" default is the bundled scenario files, not a list of names."""
    from cosim.scenario import available_scenarios
    from eval.cli import build_parser
    from eval.scale import benchmark

    envs = tuple(available_scenarios())
    assert labels.ENVS == envs
    assert protocol.ProtocolPlan().envs == envs == benchmark.BenchmarkPlan().envs
    parser = build_parser()
    assert parser.parse_args(["test"]).envs == list(envs) == parser.parse_args(["benchmark"]).envs
    assert parser.parse_args(["check-scenarios"]).scenarios == list(envs)
    assert len({labels.env_colour(e) for e in envs}) == len(envs)


def test_the_facade_reexports_the_modules_names():
    import eval.training.train as facade

    assert facade.train is __import__("eval.training.trainer").training.trainer.train
    assert facade.make_config is config.make_config and facade.RunLog is runlog.RunLog


def test_every_algorithm_has_a_preset_yaml_and_no_stray_files():
    files = {p.stem for p in presets.HYPERPARAMS.glob("*.yaml")}
    assert files == {*registry.ALGORITHMS, "runs"}


@pytest.mark.parametrize("algo", list(registry.ALGORITHMS))
def test_every_preset_yaml_loads_into_the_agent_config(algo):
    config_cls = registry.get_agent_class(algo).config_class
    defaults = config_cls().to_dict()
    entries = yaml.safe_load((presets.HYPERPARAMS / f"{algo}.yaml").read_text())
    assert set(entries) == set(presets.load_presets())
    for name, preset in presets.load_presets().items():
        hyper = entries[name].get("hyperparameters") or {}
        unknown = set(hyper) - set(defaults)
        assert not unknown, f"{algo}.yaml {name}: unknown hyperparameters {unknown}"
        for key, value in hyper.items():  # YAML reads 1e-4 as text: write 1.0e-4
            kind = type(defaults[key])
            assert (isinstance(value, kind) or (kind is float and type(value) is int)
                    or (kind is tuple and isinstance(value, list))), (algo, name, key)
        built = config_cls.preset(preset.agent_preset, reward_scale=preset.reward_scale, **hyper)
        for key, value in hyper.items():  # compared by hand: pytest.approx rejects nested values since 9.1
            assert _same_value(getattr(built, key), value), (algo, name, key, getattr(built, key), value)
        assert preset.steps[algo] >= 1


def _same_value(built, written) -> bool:
    """A preset value as the config holds it (tuples, floats) equals what the YAML wrote (lists, ints)."""
    if isinstance(written, (list, tuple)):
        return (isinstance(built, (list, tuple)) and len(built) == len(written)
                and all(_same_value(b, w) for b, w in zip(built, written, strict=True)))
    if isinstance(written, float) or isinstance(built, float):
        return math.isclose(built, written, rel_tol=1e-9, abs_tol=0.0)
    return built == written


def test_same_value_tells_nested_values_apart():
    assert _same_value((-0.6, -1.0), [-0.6, -1.0]) and _same_value(1e-4, 1.0e-4) and _same_value(3.0, 3)
    assert not _same_value((-0.6, -1.0), [-0.6, -0.9]) and not _same_value((1.0,), [1.0, 2.0])
    assert not _same_value("adam", "sgd") and not _same_value(1e-4, 1.1e-4)


def test_every_command_takes_the_presets_from_the_yaml():
    from eval.cli import build_parser
    from eval.scale import benchmark

    names = presets.preset_names()
    assert names == ("smoke", "quick", "standard", "paper")
    parser = build_parser()
    for command in ("train", "benchmark"):
        assert parser.parse_args([command, "--preset", "standard"]).preset == "standard"
        with pytest.raises(SystemExit):
            parser.parse_args([command, "--preset", "standrad"])
    assert parser.parse_args(["benchmark"]).preset == "standard"  # the benchmark's default
    assert benchmark.BenchmarkPlan().preset == "standard"
    assert set(benchmark.TEST_SETTINGS) == set(names)  # every preset says how it is tested
    root = Path(eval.__file__).resolve().parent
    for path in root.glob("*.py"):  # no second list of the names to keep in step
        text = path.read_text()
        assert '"smoke", "quick"' not in text and "smoke, quick or paper" not in text, path


def test_the_standard_budgets_are_15_minutes_at_the_measured_rates():
    """docs/benchmarks.md "Training throughput per algorithm": env steps/s per algorithm with
    the presets' 6 ACs and one frame, quiet machine (the table whose rate column says "6 ACs"),
    the rates the budgets were sized with; with 4 frames they take 27-41 minutes (the table
    above it), which the docs say. DQN's and TD3's were re-sized by a measurement of their own."""
    doc = (Path(eval.__file__).resolve().parents[1] / "docs" / "benchmarks.md").read_text()
    section = doc.split("\n## Training throughput per algorithm\n")[1]
    (table,) = [t for t in section.split("\n\n") if t.startswith("| algorithm | env steps/s (6 ACs")]
    rates = {}
    for line in table.splitlines()[2:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        rates[cells[0].split()[0].lower()] = float(cells[1])
    standard = presets.load_presets()["standard"]
    assert set(rates) == set(registry.ALGORITHMS)
    for algo, rate in rates.items():
        if algo in ("dqn", "td3"):  # re-sized 2026-11-26 by the UTD pilot (below)
            continue
        minutes = standard.steps[algo] / rate / 60
        assert 14 <= minutes <= 16, (algo, standard.steps[algo], rate, minutes)
    # DQN: one gradient step per 8 transitions, 48,000 env steps (task version 3; in git history at 1b59d82, docs/results/2026-11-26-utd-pilot)
    dqn = config.make_config("dqn", preset="standard")
    assert (dqn.steps, dqn.agent_config.train_freq) == (48000, 8)
    assert "| 8 (adopted, with 48,000 env steps) |" in doc
    # TD3: one gradient step per 8 transitions, the same 20,000 env steps (the pilot's TD3 arm)
    td3_run = config.make_config("td3", preset="standard")
    td3 = td3_run.agent_config
    assert (td3_run.steps, td3.train_freq) == (20000, 8)
    assert "| TD3 | 8 (adopted, same 20,000 env steps) |" in doc
    # DDPG: 8 measured and not adopted
    assert config.make_config("ddpg", preset="standard").agent_config.train_freq == 4
    assert "| DDPG | 4 (kept) |" in doc and "| DDPG | 8 (not adopted) |" in doc
    assert (standard.agents, standard.horizon, standard.envs, standard.frame_stack) == (6, 600, 1, 4)  # 4 frames: docs/task.md, "Observation"
    assert (td3.random_steps, td3.random_low) == (2000, (-0.6, -1.0))


def preset_comment_faults(text: str) -> list[str]:
    """What breaks the presets' comment rule in a YAML file's ``text``: after a one-line header,
    at most one comment line per value (a line of its own directly above the value's line, or at
    the end of that line, not both), and no dated result (the reasons live in
    docs/reference.md#presets, the measurements in docs/)."""
    lines = text.splitlines()
    faults = [f"line {n}: a dated result ({found.group()!r}): say why in docs/reference.md#presets"
              for n, line in enumerate(lines, 1)
              if (found := re.search(r"docs/results|git history|\b20\d\d-\d\d-\d\d\b", line))]
    for n, (line, below) in enumerate(zip(lines[1:], [*lines[2:], ""], strict=True), 2):
        if line.lstrip().startswith("#") and (not below.strip() or below.lstrip().startswith("#")
                                              or " #" in below):
            faults.append(f"line {n}: a comment not alone above its value's line")
    return faults


def test_the_preset_comment_rule_tells_a_good_file_from_a_bad_one():
    good = "# header\n\n# why\nsmoke:\n  steps: 120  # rate x 900 s\n  # why\n  agents: 2\n"
    assert preset_comment_faults(good) == []
    for bad in ("# header\n# a second line\n\nsmoke: {}\n", "# h\n# one\n# two\nsmoke: {}\n",
                "# h\n# above\nsteps: 1  # and beside\n", "# h\n# dangling\n\nsmoke: {}\n",
                "# h\nsteps: 1  # (task version 1; in git history at 1b59d82)\n",
                "# h\n# measured 2026-11-26\nsteps: 1\n"):
        assert preset_comment_faults(bad), bad


def test_every_preset_yaml_carries_one_comment_line_per_value_at_most():
    for path in sorted(presets.HYPERPARAMS.glob("*.yaml")):
        faults = preset_comment_faults(path.read_text())
        assert not faults, f"{path.relative_to(ROOT)}: {faults}"


def test_an_unknown_preset_key_is_refused_listing_the_valid_ones(tmp_path):
    for path in presets.HYPERPARAMS.glob("*.yaml"):
        (tmp_path / path.name).write_text(path.read_text())
    runs = yaml.safe_load((tmp_path / "runs.yaml").read_text())
    runs["quick"]["horizn"] = 10
    (tmp_path / "runs.yaml").write_text(yaml.safe_dump(runs))
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['horizn'\]; valid keys: .*'horizon'"):
        presets.load_presets(tmp_path)
    runs["quick"].pop("horizn")
    (tmp_path / "runs.yaml").write_text(yaml.safe_dump(runs))
    td3 = yaml.safe_load((tmp_path / "td3.yaml").read_text())
    td3["quick"]["hyperparams"] = td3["quick"].pop("hyperparameters")
    (tmp_path / "td3.yaml").write_text(yaml.safe_dump(td3))
    with pytest.raises(ValueError, match="td3.yaml: quick: unknown key"):
        presets.load_presets(tmp_path)


def test_only_the_smoke_preset_rounds_its_policy_files_and_a_bad_dtype_is_refused(tmp_path):
    """best.pt as float16 saves the smoke benchmark half its disk; every preset that measures
    something keeps exact float32 policies (agents.registry.POLICY_DTYPES)."""
    loaded = presets.load_presets()
    assert {name: p.policy_dtype for name, p in loaded.items()} == {
        "smoke": "float16", "quick": "float32", "standard": "float32", "paper": "float32"}
    assert config.make_config("ppo", preset="smoke").policy_dtype == "float16"
    for path in presets.HYPERPARAMS.glob("*.yaml"):
        (tmp_path / path.name).write_text(path.read_text())
    runs = yaml.safe_load((tmp_path / "runs.yaml").read_text())
    runs["quick"]["policy_dtype"] = "float8"
    (tmp_path / "runs.yaml").write_text(yaml.safe_dump(runs))
    with pytest.raises(ValueError, match=r"runs.yaml: quick: policy_dtype must be one of float32, float16, got 'float8'"):
        presets.load_presets(tmp_path)


def test_eval_never_writes_a_checkpoint_payload_itself():
    """Checkpoints are the agents package's format: eval saves agents (agent.save) and retunes
    them (agents.checkpoint.retune_checkpoint), never torch.save's a payload it edited."""
    writers = [f"{path.relative_to(ROOT)}:{n}" for path in sorted((ROOT / "eval").rglob("*.py"))
               for n, line in enumerate(path.read_text().splitlines(), 1) if "torch.save(" in line]
    assert not writers, writers
