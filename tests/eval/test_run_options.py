"""A run's options are declared once (eval/training/options.py, RunOptions): every field reaches
`cosim train`, `cosim benchmark` (those declared ``benchmark``), the runs of ``--algo all``, the
trials of ``--pbt`` and the report (those declared ``report``). Before, seven hand-kept lists
had drifted: ``--learner-threads`` was dropped by ``--algo all`` and ``--pbt``, ``init_from``
was not in the report."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import subprocess
from pathlib import Path

import pytest
import yaml

from eval.cli import build_parser, main
from eval.training.config import TrainConfig, resolve
from eval.training.options import RunOptions, TrainError, benchmark_names, config_keys, declared

EXAMPLE = {  # a value other than the default for every option, valid together (dqn: a replay learner)
    "algo": "dqn", "env": "env_2", "preset": "smoke", "agents": 1, "steps": 40, "seed": 3,
    "action_type": "discrete", "agent_preset": "paper", "hyper": {"action_repeat": "2"}, "envs": 2,
    "frame_stack": 2, "obs": "route", "collisions": "step", "fault": "both", "share_params": True, "stall_truncate": 25,
    "demo_steps": 30, "demo_updates": 5, "encoder": "ENCODER", "init_from": "SOURCE", "validation_episodes": 3,
    "validation_steps": 7, "select_by": "ds", "device": "cpu", "torch_threads": 1, "learner_threads": 2,
}
"""Adding an option adds its example here: the walk below fails until it does."""
WITH_DEFAULT = {"algo": {"demo_steps": 0, "demo_updates": 0}, "demo_steps": {"demo_updates": 0}}
"""Options that must go back to their defaults along with one (PPO takes no demonstrations)."""
NOT_FOR_ALL = ("init_from", "demo_steps", "demo_updates", "action_type")
"""What ``--algo all`` refuses: a warm start and demonstrations are one algorithm's, and an
action type fits only the algorithms of its kind."""


@pytest.fixture
def example(tmp_path) -> dict:
    source = tmp_path / "source"  # what --init-from accepts: a run folder with ac_0's best.pt
    (source / "checkpoints" / "ac_0").mkdir(parents=True)
    (source / "checkpoints" / "ac_0" / "best.pt").write_bytes(b"")
    encoder = tmp_path / "encoder.pt"  # what --encoder accepts when a run is resolved: a file (its hash recorded)
    encoder.write_bytes(b"an encoder")
    return {**EXAMPLE, "init_from": str(source), "encoder": str(encoder)}


def _argv(values: dict) -> list[str]:
    """The `cosim train` flags of ``values`` (option name -> value), from the declaration."""
    flags = dict(declared())
    out = []
    for name, value in values.items():
        spec = flags[name]
        if isinstance(value, bool):
            out += [spec.flag] if value else []
        elif spec.repeat:
            out += [a for k, v in value.items() for a in (spec.flag, f"{k}={v}")]
        else:
            out += [spec.flag, str(value)]
    return out


def _same_keys(a: TrainConfig, b: TrainConfig, name: str) -> bool:
    return all(getattr(a, k) == getattr(b, k) for k in config_keys(name))


@pytest.fixture
def trained(monkeypatch, tmp_path) -> list[TrainConfig]:
    """The configs `cosim train` would train (eval.training.train.train replaced)."""
    import eval.training.train

    seen: list[TrainConfig] = []

    def train(cfg, out=None, **kwargs):
        seen.append(cfg)
        return tmp_path / "run"

    monkeypatch.setattr(eval.training.train, "train", train)
    return seen


def test_the_example_names_every_option_and_the_declaration_says_each_ones_help():
    names = [n for n, _ in declared()]
    assert set(EXAMPLE) == set(names), "give each option an example value"
    commands = {a.dest: a for a in build_parser()._subparsers._group_actions[0].choices["train"]._actions}
    bench = {a.dest: a for a in build_parser()._subparsers._group_actions[0].choices["benchmark"]._actions}
    for name, spec in declared():
        assert commands[name].option_strings == [spec.flag] and commands[name].help == spec.help, name
        if spec.benchmark:
            assert bench[name].help == (spec.benchmark_help or spec.help), name
    assert "learner_threads" in names and "init_from" in names


def test_each_option_changes_what_the_run_trains_with(example):
    """Every option lands in the TrainConfig keys it declares: set, it gives another value than
    with it at its default (the rest of the example kept)."""
    options = RunOptions(**example)
    cfg = resolve(options)
    for name, _ in declared():
        keys = config_keys(name)
        if not keys:  # checked only: --action-type must be the algorithm's own kind
            assert cfg.action_type == example[name]
            with pytest.raises(TrainError, match="cannot train with continuous actions"):
                resolve(options.replace(**{name: "continuous"}))
            continue
        without = resolve(options.replace(**{name: getattr(RunOptions(), name), **WITH_DEFAULT.get(name, {})}))
        assert not _same_keys(cfg, without, name), f"{name} does not reach TrainConfig {keys}"
        if keys == (name,):
            assert getattr(cfg, name) == (str(Path(example[name]).resolve()) if name == "init_from"
                                          else example[name]), name
    assert cfg.encoder == str(Path(example["encoder"]).resolve())
    assert cfg.encoder_sha256 == hashlib.sha256(b"an encoder").hexdigest()


def test_cosim_train_sees_every_option(example, trained, tmp_path):
    argv = _argv(example)
    assert RunOptions.from_args(build_parser().parse_args(["train", *argv])) == RunOptions(**example)
    assert main(["train", *argv, "--out", str(tmp_path / "runs"), "--quiet"]) == 0
    assert trained == [resolve(RunOptions(**example))]


class _Child:
    """A `cosim train` child of ``--algo all`` that says its run folder and exits 0."""

    started: list[list[str]] = []

    def __init__(self, argv, **kwargs):
        self.argv, self.returncode = argv, 0
        self.stdout = io.StringIO("run folder: somewhere\n")
        _Child.started.append(argv)

    def poll(self):
        return 0


def test_the_runs_of_algo_all_see_every_option_they_take(example, trained, monkeypatch, tmp_path, capsys):
    from eval.cli.learn import _run_options
    from eval.training.config import ALGORITHMS

    monkeypatch.setattr(subprocess, "Popen", _Child)
    _Child.started = []
    given = {n: v for n, v in example.items() if n not in (*NOT_FOR_ALL, "algo")}
    out = str(tmp_path / "runs")
    assert main(["train", "--algo", "all", *_argv(given), "--out", out, "--quiet"]) == 0
    parent = RunOptions(**given, algo="all")
    assert [c[3] for c in _Child.started] == ["train"] * len(ALGORITHMS)
    for argv, algo in zip(_Child.started, ALGORITHMS, strict=True):
        child = _run_options(build_parser().parse_args(argv[3:]))
        assert child == parent.for_algo(algo), algo  # the object, every option in it
        assert child.learner_threads == 2 and child.share_params == (algo not in ("a3c", "impala"))
    trained.clear()
    for argv in _Child.started:  # each child trains what the parent resolved for it
        assert main(argv[3:]) == 0
    assert trained == [resolve(parent.for_algo(a)) for a in ALGORITHMS]
    capsys.readouterr()
    for name in NOT_FOR_ALL:  # refused in one line before any run starts
        _Child.started = []
        assert main(["train", "--algo", "all", *_argv({name: example[name]}), "--out", out, "--quiet"]) == 2
        assert capsys.readouterr().err.count("\n") == 1 and not _Child.started, name


def test_a_child_given_its_options_takes_no_run_flag_beside_them(capsys):
    options = RunOptions(algo="dqn", preset="smoke").to_json()
    assert main(["train", "--options", options, "--learner-threads", "2", "--quiet"]) == 2
    assert "give --learner-threads there, not as flags beside it" in capsys.readouterr().err


def test_the_trials_of_pbt_see_every_option(example, monkeypatch, tmp_path, trained):
    import eval.scale.pbt
    import eval.scale.raysession

    population = []
    monkeypatch.setattr(eval.scale.raysession, "ray_available", lambda: True)
    monkeypatch.setattr(eval.scale.pbt, "run_pbt", lambda cfg, *a, **k: population.append(cfg) or tmp_path)
    assert main(["train", "--pbt", "2", *_argv(example), "--out", str(tmp_path / "runs")]) == 0
    (cfg,) = population
    trial = TrainConfig(**cfg.to_dict())  # what each trial builds from Ray's config (eval/scale/pbt.py)
    assert trial == cfg == resolve(RunOptions(**example))
    assert trial.learner_threads == 2 and trial.init_from == str(Path(example["init_from"]).resolve())


def test_cosim_benchmark_sees_the_options_declared_for_it_and_refuses_the_others(example, monkeypatch, tmp_path):
    import eval.scale.benchmark as benchmark

    plans = []
    monkeypatch.setattr(benchmark, "run_sequential", lambda plan, out, **k: plans.append(plan) or {})
    taken = {n: example[n] for n in benchmark_names()}
    out = tmp_path / "bench"
    assert main(["benchmark", "--no-ray", "--train-only", "--envs", "env_2", "--algos", "dqn", "--out", str(out),
                 *_argv(taken)]) == 0
    (plan,) = plans
    (cell,) = plan.cells()
    train = resolve(RunOptions(**example))
    for name, spec in declared():
        if spec.benchmark:
            assert getattr(plan, name) == example[name] and _same_keys(cell, train, name), name
        else:
            assert getattr(plan.options, name) == getattr(RunOptions(), name), name
            with pytest.raises(benchmark.BenchmarkError, match="not an option of `cosim benchmark`"):
                benchmark.BenchmarkPlan(options=RunOptions(**{name: example[name]}))
    (out / "benchmark.json").write_text(json.dumps(plan.to_dict()))
    assert benchmark.load_plan(out) == plan  # --resume reads every one of them back
    assert cell.demo_updates == benchmark.DEMO_UPDATES  # the demonstration variant's pre-training


def test_the_report_says_the_options_declared_for_it(example, tmp_path):
    from eval.reporting.report import TRAINING_KEYS, trained_with

    cfg = resolve(RunOptions(**example))
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict()))
    said = trained_with(run)
    for name, spec in declared():
        for key in config_keys(name):
            assert (said.get(key) == getattr(cfg, key)) if spec.report else key not in said, (name, key)
    assert said["init_from"] == cfg.init_from and "learner_threads" not in said
    assert set(TRAINING_KEYS) - {f.name for f in dataclasses.fields(TrainConfig)} == set()


def test_every_option_refuses_a_value_out_of_its_range_naming_its_flag():
    for name, spec in declared():
        bad = (spec.low - 1 if spec.low is not None else "nope" if spec.choices is not None else None)
        if bad is None:
            continue
        with pytest.raises(TrainError, match=f"^{spec.flag} must be "):
            RunOptions(**{name: bad})
    with pytest.raises(TrainError, match="unknown option"):
        RunOptions.from_json('{"learner_thread": 2}')


def test_the_presets_are_the_one_source_of_the_frame_stack_and_the_episode_length(tmp_path):
    """No code default stands in for runs.yaml's frame_stack or horizon: a preset without one is
    refused naming the key."""
    from eval.training import presets

    for path in presets.HYPERPARAMS.glob("*.yaml"):
        (tmp_path / path.name).write_text(path.read_text())
    runs = yaml.safe_load((tmp_path / "runs.yaml").read_text())
    assert all({"frame_stack", "horizon"} <= set(p) for p in runs.values())
    del runs["quick"]["frame_stack"], runs["quick"]["horizon"]
    (tmp_path / "runs.yaml").write_text(yaml.safe_dump(runs))
    with pytest.raises(presets.PresetError, match=r"quick: missing key\(s\) \['horizon', 'frame_stack'\]"):
        presets.load_presets(tmp_path)
