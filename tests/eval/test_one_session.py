"""One test session (issue 58): `cosim test`, `cosim benchmark`'s report and the science study
run their episodes through one function, eval.testing.session.run_test, and nothing else in
the product or the studies runs the protocol's jobs itself."""

import ast
from pathlib import Path

import pytest

import eval
from cosim.errors import CosimError
from eval.cli import main
from eval.scale.benchmark import BenchmarkPlan, cell_name, write_report
from eval.testing import session
from eval.testing.protocol import ProtocolError, ProtocolPlan
from eval.testing.session import TestRequest
from eval.testing.validity import HELD_OUT_SEED

ROOT = Path(eval.__file__).resolve().parents[1]


class Called(CosimError):
    """Raised by the stand-in run_test: the caller got as far as the session (a CosimError:
    `cosim` prints it as a user error and exits 2)."""


def _run(folder: Path) -> None:
    """A run folder whose ac_0 has a checkpoint file (never loaded: the session is not run)."""
    ckpt = folder / "checkpoints" / "ac_0"
    ckpt.mkdir(parents=True)
    (ckpt / "best.pt").write_bytes(b"")


def test_cosim_test_the_benchmark_report_and_the_study_call_the_one_session(tmp_path, monkeypatch, load_study):
    asked: list[tuple[str, TestRequest]] = []

    def stand_in(request, *args, **kwargs):
        asked.append((caller, request))
        raise Called

    monkeypatch.setattr(session, "run_test", stand_in)

    caller = "cosim test"
    assert main(["test", "--policy", "autopilot", "--agents", "2", "--envs", "env_1", "--quiet",
                 "--out", str(tmp_path / "reports")]) == 2

    caller = "benchmark"
    plan = BenchmarkPlan(preset="smoke", envs=("env_1",), algos=("ppo", "dqn"), seeds=1)
    for algo in plan.algos:
        _run(tmp_path / "bench" / "runs" / f"env_1__{algo}__0__bench")
    with pytest.raises(Called):
        write_report(plan, tmp_path / "bench")

    caller = "study"
    science = load_study("science")
    for algo in plan.algos:
        _run(tmp_path / "study" / "bench" / "runs" / cell_name({"env": "env_1", "algo": algo, "seed": 0}))
    study = {"test": {"scenarios": [1], "episodes": 2, "steps": 30}}
    with pytest.raises(Called):
        science.test(plan, study, tmp_path / "study", print, {"env_1": [0]}, workers=2)

    assert [c for c, _ in asked] == ["cosim test", "benchmark", "study"]
    (_, cli), (_, bench), (_, study_request) = asked
    assert cli.policy == "autopilot" and cli.algos == ("ppo", "a3c") and cli.plan.envs == ("env_1",)
    assert cli.replays and cli.references and cli.checkpoints is None
    for request, root in ((bench, tmp_path / "bench"), (study_request, tmp_path / "study" / "bench")):
        assert request.policy == "trained" and request.algos == ("ppo", "dqn")
        assert request.plan.seed == HELD_OUT_SEED and request.plan.envs == ("env_1",)
        assert request.checkpoints == {"env_1": {a: root / "runs" / f"env_1__{a}__0__bench" / "checkpoints"
                                                 / "ac_0" / "best.pt" for a in ("ppo", "dqn")}}
    assert bench.references and not study_request.references and study_request.workers == 2
    assert (study_request.plan.scenarios, study_request.plan.episodes) == ((1,), 2)


def _calls_of(path: Path, name: str) -> list[int]:
    tree = ast.parse(path.read_text(), str(path))
    return [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Call)
            and (getattr(n.func, "id", None) == name or getattr(n.func, "attr", None) == name)]


def test_only_the_session_runs_the_protocols_jobs():
    sources = [*(ROOT / "eval").rglob("*.py"), *(ROOT / "studies").glob("*.py")]
    callers = {str(p.relative_to(ROOT)): lines for p in sources if (lines := _calls_of(p, "run_protocol"))}
    assert set(callers) == {"eval/testing/session.py"}, callers


def test_a_request_names_what_is_missing_or_does_not_fit():
    plan = ProtocolPlan(envs=("env_1", "env_2"))
    with pytest.raises(ProtocolError, match="no checkpoint given for env_2: dqn"):
        TestRequest(plan, ("ppo", "dqn"), checkpoints={"env_1": {"ppo": Path("a"), "dqn": Path("b")},
                                                        "env_2": {"ppo": Path("a")}})
    with pytest.raises(ProtocolError, match="checkpoints are for policy 'trained', not 'random'"):
        TestRequest(plan, ("ppo",), policy="random", checkpoints={"env_1": {"ppo": Path("a")}})
    with pytest.raises(ProtocolError, match="unknown policy kind 'scripted'"):
        TestRequest(plan, ("ppo",), policy="scripted")
    with pytest.raises(ProtocolError, match="give run_test an out"):
        session.run_test(TestRequest(plan, ("ppo",), policy="random", replays=True))
    assert TestRequest(plan, ("ppo",), policy="autopilot").slots is None
