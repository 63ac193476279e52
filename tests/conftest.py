"""Test-session set-up shared by every tier, and the fixture that loads a study script.

A test run started in the background by a non-interactive shell (``pytest ... &`` in a
script, ``nohup``, some CI runners) inherits SIGINT *ignored*, and so does every process
it starts: a Ctrl-C sent to a trainer under test would be lost and the trainer would run
on (the three signal tests of issue 24 hung or finished with exit code 0 exactly so).
Python installs its KeyboardInterrupt handler only where SIGINT is not ignored, so the
session puts it back; processes the tests start then get SIGINT's default and handle it.
"""

import importlib.util
import signal
import sys
from pathlib import Path

import pytest

if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

STUDIES = Path(__file__).resolve().parents[1] / "studies"


@pytest.fixture(scope="session")
def load_study():
    """``load_study(name)``: the script ``studies/<name>.py`` as a module (studies/ is not a
    package). It is registered in ``sys.modules`` (a dataclass looks its module up there) and
    studies/ is put on ``sys.path`` (a study imports its siblings). The tests of the studies
    (tests/studies/) use it, and tests/eval/test_one_session.py (the study calls the one test
    session)."""

    def load(name: str):
        if str(STUDIES) not in sys.path:
            sys.path.insert(0, str(STUDIES))
        spec = importlib.util.spec_from_file_location(name, STUDIES / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture(scope="session")
def seed_frame():
    """``seed_frame(values, algo="ppo", env="env_1")``: hand-made seed means (as
    eval.reporting.multiseed.seed_means gives), one row per seed of Scenario 1; every metric 0.5
    but those of ``values`` (metric -> one value per seed)."""
    import pandas as pd

    from eval.reporting.multiseed import METRICS

    def make(values: dict, algo: str = "ppo", env: str = "env_1") -> pd.DataFrame:
        n = len(next(iter(values.values())))
        base = {m: [0.5] * n for m in METRICS}
        base.update(values)
        return pd.DataFrame({"scenario": 1, "env": env, "algorithm": algo, "train_seed": range(n), **base})

    return make


@pytest.fixture(scope="session")
def reference_frame():
    """``reference_frame(env="env_1", values=None)``: a hand-made reference long table (as
    eval.reporting.multiseed.reference_table gives): every policy's mean return, goal rate,
    driving score and turning slots' route completion in ``env`` (``values``: policy -> a tuple
    of those, 0 where left out)."""
    import pandas as pd

    from eval.reporting.multiseed import fmt
    from eval.testing.validity import POLICIES

    metrics = ("return", "goal", "DS", "RC_turning")

    def make(env: str = "env_1", values: dict | None = None) -> pd.DataFrame:
        values = values or {}
        rows = []
        for p in POLICIES:
            given = tuple(values.get(p, ()))
            for m, v in zip(metrics, given + (0.0,) * (len(metrics) - len(given)), strict=True):
                rows.append({"scenario": 1, "env": env, "kind": "reference", "name": p, "metric": m,
                             "mean": v, "ci_low": v, "ci_high": v, "n": 3, "cell": fmt(m, v, v, v)})
        return pd.DataFrame(rows)

    return make
