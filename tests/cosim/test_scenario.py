"""Scenario files: loading, validation, and scenarios that live outside the package."""

import shutil
from pathlib import Path

import pytest
import yaml

from cosim.errors import NetError, ScenarioError
from cosim.scenario import Contact, available_scenarios, load_scenario, nets_dir, scenario_data

ENVS = ["env_1", "env_2", "env_3", "env_4", "env_5"]


def test_bundled_scenarios_load():
    assert available_scenarios() == ENVS
    titles = [load_scenario(n).title for n in ENVS]
    assert titles == ["Straight", "Three-way", "Four-way", "Roundabout", "Merge"]
    for n in ENVS:
        sc = load_scenario(n)
        assert sc.max_agents == 6 and sc.net.exists()
        assert sc.pedestrians == (n in ("env_2", "env_3"))


def test_unknown_scenario_lists_the_available_ones():
    with pytest.raises(ScenarioError, match="env_1, env_2, env_3, env_4, env_5"):
        load_scenario("env_9")


def _copy_yaml(tmp_path: Path, name="env_3", edit=None) -> Path:
    data = scenario_data(name)  # absolute paths, so the copy can live anywhere
    if edit:
        edit(data)
    out = tmp_path / f"{name}_copy.yaml"
    out.write_text(yaml.safe_dump(data))
    return out


def test_solid_cars_and_the_contact_rule_are_read_from_the_yaml_and_the_defaults_everywhere(tmp_path):
    assert not load_scenario(_copy_yaml(tmp_path, edit=lambda d: d.update(solid_cars=False))).solid_cars
    assert all(load_scenario(f"env_{k}").solid_cars for k in range(1, 6))  # task version 4
    sc = load_scenario(_copy_yaml(tmp_path, edit=lambda d: d.update(
        contact={"charge": "step", "window": 2.0, "fault": "both"})))
    assert (sc.contact.charge, sc.contact.window, sc.contact.fault) == ("step", 2.0, "both")
    assert all(load_scenario(f"env_{k}").contact == Contact() for k in range(1, 6))
    assert (Contact().charge, Contact().window, Contact().fault) == ("event", 5.0, "at_fault")  # task version 5
    with pytest.raises(ScenarioError, match="charge must be one of event, step"):
        load_scenario(_copy_yaml(tmp_path, edit=lambda d: d.update(contact={"charge": "once"})))
    with pytest.raises(ScenarioError, match=r"unknown key\(s\) \['windw'\]"):
        load_scenario(_copy_yaml(tmp_path, edit=lambda d: d.update(contact={"windw": 5})))


def test_cars_see_acs_is_read_from_the_yaml_and_on_in_every_bundled_scenario(tmp_path):
    assert not load_scenario(_copy_yaml(tmp_path, edit=lambda d: d.update(cars_see_acs=False))).cars_see_acs
    assert all(load_scenario(f"env_{k}").cars_see_acs for k in range(1, 6))  # task version 4


def test_scenario_data_makes_every_file_absolute_or_relative_to_the_copys_folder(tmp_path):
    data = scenario_data("env_3")
    files = [data["net"], *data["demand"], *data["pedestrian_demand"], *data["additional"]]
    assert all(Path(f).is_absolute() and Path(f).exists() for f in files)
    near = scenario_data("env_3", relative_to=tmp_path)
    assert not Path(near["net"]).is_absolute() and (tmp_path / near["net"]).resolve() == Path(data["net"])
    with pytest.raises(ScenarioError, match="unknown scenario 'env_9'; available: env_1"):
        scenario_data("env_9")


def test_malformed_yaml_names_the_file(tmp_path):
    bad = tmp_path / "broken.yaml"
    bad.write_text("name: x\nacs: [ {route: [a, b}\n")
    with pytest.raises(ScenarioError, match="broken.yaml.*malformed YAML"):
        load_scenario(bad)


def test_unknown_key_lists_valid_keys(tmp_path):
    path = _copy_yaml(tmp_path, edit=lambda d: d["termination"].update(on_colision=True))
    with pytest.raises(ScenarioError, match=r"on_colision.*valid keys: \[.*on_collision"):
        load_scenario(path)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d.update(dt=-0.1), "dt must be in"),
        (lambda d: d.update(horizon="long"), "'horizon' must be int"),
        (lambda d: d.update(net="missing.net.xml"), "missing.net.xml.*does not exist"),
        (lambda d: d["acs"].append(d["acs"][0]) or d["acs"].extend(d["acs"][:1]), "1 to 6"),
        (lambda d: d["acs"][0].update(route=["tx_e", "nowhere"]), "'nowhere' is not in"),
        (lambda d: d["acs"][0].update(route=["tx_e", "xs_n"]), "not connected"),
        (lambda d: d["acs"][0].update(lane=3), "lane 3 does not exist"),
        (lambda d: d["acs"][0].update(depart_speed=-2), r"acs\[0\].*depart_speed must be 0..25"),
        (lambda d: d["acs"][0].update(depart_speed=40), r"depart_speed must be 0..25.0 m/s"),
        (lambda d: d.update(spawn_jitter={"heading_deg": 90}), r"'spawn_jitter'.*heading_deg must be 0..45"),
        (lambda d: d.update(spawn_jitter={"lateral_m": 1}), r"'spawn_jitter'.*unknown key.*lateral"),
        (lambda d: d.update(solid_cars="yes"), r"'solid_cars' must be bool"),
        (lambda d: d.update(cars_see_acs=1), r"'cars_see_acs' must be bool"),
    ],
)
def test_bad_values_name_file_and_key(tmp_path, edit, message):
    path = _copy_yaml(tmp_path, edit=edit)
    with pytest.raises(ScenarioError, match=message) as err:
        sc = load_scenario(path)
        from cosim.roadmap import RoadMap

        RoadMap(sc)  # route checks happen when the road map is built
    assert "env_3_copy.yaml" in str(err.value)


def test_malformed_net_names_the_file(tmp_path):
    net = tmp_path / "broken.net.xml"
    net.write_text("<net><edge id='a'>")
    path = _copy_yaml(tmp_path, edit=lambda d: d.update(net=str(net)))
    from cosim.world import World

    with pytest.raises(NetError, match="broken.net.xml"):
        World(load_scenario(path))


def test_scenario_outside_the_package_with_an_edited_edge(tmp_path):
    """A copy of env_1 on a rebuilt net where the straight got a third lane: no code change."""
    from cosim import nets
    from cosim.world import World

    town = tmp_path / "town"
    shutil.copytree(nets_dir() / "town", town)
    edg = town / "town.edg.xml"
    edg.write_text(edg.read_text().replace(
        '<edge id="st_e"  from="SW"  to="XN"  type="avenue"/>',
        '<edge id="st_e"  from="SW"  to="XN"  type="avenue" numLanes="3"/>',
    ))
    with pytest.raises(NetError, match="town.edg.xml changed"):
        nets.check([town / "town.netccfg"])
    nets.build(town / "town.netccfg")
    nets.check([town / "town.netccfg"])

    def edit(d):
        d["net"] = str(town / "town.net.xml")
        d["acs"] = [{"route": ["st_e"], "depart_pos": 15, "arrival_pos": -15, "lane": 2}]

    sc = load_scenario(_copy_yaml(tmp_path, "env_1", edit))
    with pytest.raises(ScenarioError, match="lane 2 does not exist"):  # the bundled net: 2 lanes
        World(load_scenario("env_1").with_overrides(acs=sc.acs))
    with World(sc, 1) as w:
        w.reset(seed=3)
        x0, y0, _, _ = w.ac_state("ac_0")
        for _ in range(30):
            res = w.step({"ac_0": (1.0, 0.0)})
        assert res["ac_0"].x > x0 + 10 and not res["ac_0"].events.wrong_lane
        assert not res["ac_0"].events.off_road
