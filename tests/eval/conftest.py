"""Fixtures shared by the tests of eval/ and of the study scripts in studies/."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

STUDIES = Path(__file__).resolve().parents[2] / "studies"


@pytest.fixture(scope="session")
def load_study():
    """``load_study(name)``: the script ``studies/<name>.py`` as a module (studies/ is not a
    package). It is registered in ``sys.modules`` (a dataclass looks its module up there) and
    studies/ is put on ``sys.path`` (a study imports its siblings)."""

    def load(name: str):
        if str(STUDIES) not in sys.path:
            sys.path.insert(0, str(STUDIES))
        spec = importlib.util.spec_from_file_location(name, STUDIES / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        return module

    return load
