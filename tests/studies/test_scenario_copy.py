"""studies/scenario_copy.py: a bundled scenario copied elsewhere with keys changed."""

from __future__ import annotations

import pytest

from cosim.scenario import load_scenario


@pytest.fixture(scope="module")
def copier(load_study):
    return load_study("scenario_copy")


def test_a_copy_elsewhere_loads_with_the_change_and_the_same_files(copier, tmp_path):
    out = copier.copy_scenario("env_3", tmp_path / "far" / "env_3_soft.yaml", {"solid_cars": False})
    copy, bundled = load_scenario(out), load_scenario("env_3")
    assert bundled.solid_cars and not copy.solid_cars  # solid by default since task version 4
    assert copy.net == bundled.net and copy.demand == bundled.demand and copy.additional == bundled.additional
    assert copy.acs == bundled.acs


def test_a_bad_change_is_refused_and_nothing_is_written(copier, tmp_path):
    with pytest.raises(SystemExit, match=r"'solid_cars' must be bool"):
        copier.main(["env_3", str(tmp_path / "x.yaml"), "--set", "solid_cars=maybe"])
    assert not list(tmp_path.iterdir())
    with pytest.raises(SystemExit, match="scenario_copy: unknown scenario 'env_9'; available: env_1"):
        copier.main(["env_9", str(tmp_path / "x.yaml")])
