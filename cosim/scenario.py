"""Scenarios: one YAML file per driving environment, loaded into frozen dataclasses.

A scenario names its SUMO files (network, demand, static objects), the region of
the network it covers, the learning cars' (ACs') spawn lanes, routes and goals,
the reward weights and the termination rules. Adding an environment means adding
SUMO files and one YAML; no code changes. Paths inside a YAML are relative to
the YAML file. An optional ``vehicle:`` block changes the learning cars'
``VehicleParams`` by field name (angles in degrees), e.g. the steering before
issue 25: ``vehicle: {discrete_steer_reference: 35, max_lateral_accel: null}``.

Example (``sumo_nets/scenarios/env_3.yaml``)::

    name: env_3
    title: Four-way
    net: ../town/town.net.xml
    demand: [../demand/env_3.rou.xml]
    additional: [../town/objects.add.xml]
    region: {center: [0.0, 0.0], size: [220.0, 220.0]}
    acs:
      - {route: [tx_e, xr_e], depart_pos: -45, arrival_pos: 50}
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from cosim.dynamics import VehicleParams
from cosim.errors import ScenarioError

MAX_ACS = 6
MAX_DEPART_SPEED = VehicleParams.max_speed  # m/s, what the learning car's dynamics allow
VEHICLE_ANGLES = ("max_steer", "discrete_steer_reference")
"""VehicleParams fields given in degrees in a scenario's ``vehicle:`` block (radians in code)."""
GRIP_OFF = (None, "off")
"""``vehicle: {max_lateral_accel: null}`` (or ``off``): no grip limit, the wheel angle is what
the steer commands at any speed (as before issue 25); stored as ``math.inf``."""


def nets_dir() -> Path:
    """The folder holding the bundled network, demand and scenario files."""
    return Path(str(resources.files("sumo_nets")))


def scenarios_dir() -> Path:
    return nets_dir() / "scenarios"


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the named reward terms (SPEC §3): R = sum of weight * term."""

    collision: float = -50.0
    """Per collision event with a vehicle, road object or pedestrian (``Contact.charge``)."""
    efficiency: float = 10.0
    """Multiplies (progress towards the goal in metres + forward speed / speed limit)."""
    lane: float = -0.5
    """Per step off the road or outside the lanes of the AC's own travel direction."""
    step: float = -1.0
    """Constant per-step penalty (phi) that pushes the car to make progress."""
    red_light: float = 0.0
    """Per crossing of a stop line against a red signal. 0 keeps the paper's reward; the
    event is always measured and reported as the RL metric (docs/scenarios.md)."""


@dataclass(frozen=True)
class Termination:
    """When an AC's episode ends early."""

    on_collision: bool = False
    """End the AC's episode at its first collision (charged once). Off (the default): the test's
    rule, used in training too, the episode goes on and each collision event is charged once
    (``Contact``); on: the paper's training rule (``cosim train --collisions end``). Why:
    docs/task.md, "Collision rule"."""
    on_goal: bool = True
    """End the AC's episode when it reaches its goal."""
    on_offroad: bool = False
    """End the AC's episode when it leaves the drivable surface."""
    out_of_region: bool = True
    """End the AC's episode when it leaves the scenario region (there is no world beyond it)."""
    goal_radius: float = 3.0
    """Metres from the goal point that count as reached."""
    stall_truncate: int = 0
    """A training option, off (0) in every scenario and in the test: truncate every active AC's
    episode once all of them have stood still (below 0.1 m/s, and not waiting at a red or
    yellow signal within 30 m ahead) for this many consecutive steps. Truncated, not
    terminated: the learners bootstrap from the standing state's value, as at the horizon, so
    the return the test charges is unchanged and the next episode starts instead of the
    steps left of standing (``cosim train --stall-truncate N``; docs/task.md, Collision rule)."""

    def __post_init__(self) -> None:
        if not self.goal_radius > 0:
            raise ValueError(f"goal_radius must be > 0 metres, got {self.goal_radius}")
        if isinstance(self.stall_truncate, bool) or not isinstance(self.stall_truncate, int) or self.stall_truncate < 0:
            raise ValueError(f"stall_truncate must be a whole number of steps >= 0 (0: off), got {self.stall_truncate!r}")


CONTACT_CHARGES = ("event", "step")
"""``Contact.charge``: once per collision event (the default) or every step in contact."""
CONTACT_FAULTS = ("both", "at_fault")
"""``Contact.fault``: who of a vehicle contact the reward charges (docs/task.md, "Collision rule")."""


@dataclass(frozen=True)
class Contact:
    """How a contact is charged (docs/task.md, "Collision rule")."""

    charge: str = "event"
    """``event`` (the default since task version 4): the collision weight once per collision
    event, one event per other actor, the same actor again within ``window`` seconds of its last
    charged event being the same event (the CARLA Leaderboard's count); ``step``: every step in
    contact (task version 3, ``cosim train --collisions step``)."""
    window: float = 5.0
    """Seconds after a charged event with one actor during which contact with it is that event."""
    fault: str = "at_fault"
    """Who of a vehicle contact the reward charges: ``at_fault`` (the default since task version
    5): an AC only when it drove into the other (it moved at >= 0.5 m/s and the other's centre
    lies ahead of its own), as nuPlan counts at-fault collisions; ``both`` (task version 4):
    every AC in the contact (``cosim train --fault both``). The test's driving score counts every
    event a car is in either way (Events.event_vehicle)."""

    def __post_init__(self) -> None:
        if self.charge not in CONTACT_CHARGES:
            raise ValueError(f"charge must be one of {', '.join(CONTACT_CHARGES)}, got {self.charge!r}")
        if self.fault not in CONTACT_FAULTS:
            raise ValueError(f"fault must be one of {', '.join(CONTACT_FAULTS)}, got {self.fault!r}")
        if not 0.0 < self.window < float("inf"):
            raise ValueError(f"window must be a finite number of seconds > 0, got {self.window!r}")


@dataclass(frozen=True)
class ACSpec:
    """Where one learning car starts and where it must go."""

    route: tuple[str, ...]
    """SUMO edge ids from the spawn edge to the goal edge, consecutive and connected."""
    depart_pos: float = 10.0
    """Spawn position along the first edge in metres; negative counts back from its end."""
    arrival_pos: float = -10.0
    """Goal position along the last edge in metres; negative counts back from its end."""
    lane: int = 0
    """Lane of the first edge, counted among the lanes cars may use, 0 = rightmost."""
    depart_speed: float = 0.0
    """Forward speed in m/s at the spawn point (SUMO's departSpeed); 0 = start standing."""

    def __post_init__(self) -> None:
        if not self.route:
            raise ValueError("route must name at least one edge")
        if self.lane < 0:
            raise ValueError(f"lane must be >= 0, got {self.lane}")
        if not 0.0 <= self.depart_speed <= MAX_DEPART_SPEED:
            raise ValueError(
                f"depart_speed must be 0..{MAX_DEPART_SPEED} m/s (the learning car's top speed), "
                f"got {self.depart_speed}"
            )


@dataclass(frozen=True)
class Region:
    """Axis-aligned box of the network that the environment simulates and renders."""

    center: tuple[float, float]
    size: tuple[float, float]

    def __post_init__(self) -> None:
        if len(self.center) != 2 or len(self.size) != 2:
            raise ValueError("center and size must be [x, y] pairs")
        if min(self.size) <= 0:
            raise ValueError(f"size must be positive, got {list(self.size)}")

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax)."""
        cx, cy = self.center
        hx, hy = self.size[0] / 2, self.size[1] / 2
        return cx - hx, cy - hy, cx + hx, cy + hy

    def contains(self, x: float, y: float) -> bool:
        xmin, ymin, xmax, ymax = self.bounds
        return xmin <= x <= xmax and ymin <= y <= ymax


@dataclass(frozen=True)
class Background:
    """Auto-controlled background traffic."""

    enabled: bool = True
    """Whether the demand's background cars run at all."""
    scale: float = 1.0
    """Multiplies every flow rate of the demand files (SUMO --scale)."""

    def __post_init__(self) -> None:
        if self.scale < 0:
            raise ValueError(f"scale must be >= 0, got {self.scale}")


@dataclass(frozen=True)
class SpawnJitter:
    """Seeded random offsets of every AC's spawn pose, drawn anew at each reset.

    With none, an AC starts exactly on its lane's centre line, facing along it;
    on a straight road an open-loop "full throttle, wheel straight" then keeps
    its lane. Offsets make a car steer back into its lane.
    """

    heading_deg: float = 0.0
    """Heading offset drawn uniformly from [-heading_deg, heading_deg] degrees."""
    lateral: float = 0.0
    """Sideways offset drawn uniformly from [-lateral, lateral] metres."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.heading_deg <= 45.0:
            raise ValueError(f"heading_deg must be 0..45 degrees, got {self.heading_deg}")
        if not 0.0 <= self.lateral <= 2.0:
            raise ValueError(f"lateral must be 0..2 metres, got {self.lateral}")


@dataclass(frozen=True)
class Scenario:
    """One driving environment: a region of a SUMO network plus ACs, demand and rules."""

    name: str
    """Short id, e.g. env_3."""
    net: Path
    """The built SUMO network (.net.xml)."""
    region: Region
    """The part of the network this environment covers."""
    acs: tuple[ACSpec, ...]
    """Spawn/goal of up to six learning cars; an env with N ACs uses the first N."""
    title: str = ""
    """Human name, e.g. Four-way."""
    description: str = ""
    demand: tuple[Path, ...] = ()
    """SUMO route files with the background car flows."""
    pedestrian_demand: tuple[Path, ...] = ()
    """SUMO route files with the person flows (loaded only when `pedestrians` is true)."""
    additional: tuple[Path, ...] = ()
    """SUMO additional files; polygons in them are the static road objects."""
    dt: float = 0.1
    """Simulation step in seconds (SUMO step length and ego dynamics step)."""
    horizon: int = 600
    """Steps per episode before truncation."""
    warmup: float = 30.0
    """Simulated seconds of background traffic before the ACs appear."""
    speed_limit: float = 13.89
    """m/s; the speed term of the reward is the speed along the route / speed_limit, clipped to
    [-1, 1] (negative when driving against the route; cosim.events.reward_terms)."""
    background: Background = field(default_factory=Background)
    pedestrians: bool = False
    """Whether the pedestrian demand runs (env_2 and env_3)."""
    solid_cars: bool = True
    """Whether cars are solid for an AC, as road objects are: an AC whose move brings it into
    contact with a vehicle ahead of it (its centre in front of the AC's; one the AC did not
    already touch before the move) is put back 1 m behind where it was before the step
    (cosim.world.BACK_OFF), standing, with no progress credited for that step. On by default since task version 4, so that no AC drives
    through a car for one charge (docs/task.md, "Collision rule"); off: an AC can drive through
    a car (task version 3)."""
    cars_see_acs: bool = True
    """Whether SUMO's background cars and people stop for an AC's body in their path wherever it
    is, not only for one SUMO has mapped onto their lane as their leader: a car on a lane is held
    (speed 0) while an AC's body, its centre ahead of the car's front, lies on the car's path
    ahead within its stopping distance + SEE_BUFFER m (cosim/sumo_bridge.py
    ``SumoBridge._cars_seeing``); a person is held while a moving AC's body lies on its next
    PERSON_AHEAD m of walk (``SumoBridge._people_seeing``). On by default since task version 4
    (``false``: task version 3's traffic, to which an AC standing across or beside a lane is
    invisible). docs/task.md, "Cars that see an AC anywhere"."""
    reward: RewardWeights = field(default_factory=RewardWeights)
    contact: Contact = field(default_factory=Contact)
    """How a contact is charged (once per event by default) and who is charged."""
    termination: Termination = field(default_factory=Termination)
    spawn_jitter: SpawnJitter = field(default_factory=SpawnJitter)
    """Random spawn-pose offsets per reset (none by default)."""
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    """The learning cars' geometry, limits and steering (``cosim.dynamics.VehicleParams``); a
    YAML ``vehicle:`` block overrides fields by name (:data:`VEHICLE_ANGLES` in degrees,
    ``max_lateral_accel: null`` = no grip limit); default: the defaults."""
    source: Path | None = None
    """The YAML file this scenario was read from."""

    def __post_init__(self) -> None:
        if not 0 < self.dt <= 1.0:
            raise ValueError(f"dt must be in (0, 1] seconds, got {self.dt}")
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1 step, got {self.horizon}")
        if self.warmup < 0:
            raise ValueError(f"warmup must be >= 0 seconds, got {self.warmup}")
        if not 1 <= len(self.acs) <= MAX_ACS:
            raise ValueError(f"acs must list 1 to {MAX_ACS} learning cars, got {len(self.acs)}")
        if self.speed_limit <= 0:
            raise ValueError(f"speed_limit must be > 0 m/s, got {self.speed_limit}")
        fast = [i for i, ac in enumerate(self.acs) if ac.depart_speed > self.vehicle.max_speed]
        if fast:
            raise ValueError(f"acs[{fast[0]}].depart_speed {self.acs[fast[0]].depart_speed} m/s is above "
                             f"vehicle.max_speed {self.vehicle.max_speed} m/s")

    @property
    def max_agents(self) -> int:
        return len(self.acs)

    def with_overrides(self, **changes: Any) -> Scenario:
        """A copy with some fields replaced (e.g. ``background=Background(enabled=False)``)."""
        return dataclasses.replace(self, **changes)


def available_scenarios() -> list[str]:
    """Names of the bundled scenarios, sorted."""
    return sorted(p.stem for p in scenarios_dir().glob("*.yaml"))


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a bundled scenario by name (``env_3``) or any scenario YAML by path.

    Raises:
        ScenarioError: unknown name (the message lists the available ones), unreadable
            or malformed YAML, unknown keys (listing the valid ones), bad values, or
            files it names that do not exist. The message names the file.
    """
    path = scenario_file(name_or_path)
    return _scenario_from_dict(_read_mapping(path), path)


FILE_KEYS = ("net", "additional", "demand", "pedestrian_demand")
"""The scenario keys that name files, each relative to the YAML's folder."""


def scenario_data(name_or_path: str | Path, relative_to: Path | None = None) -> dict[str, Any]:
    """A scenario YAML's mapping as the start of a variant written elsewhere (a pilot's
    ``solid_cars: true``, a test's bad value): its file paths made absolute, or relative to
    ``relative_to``, the folder the copy will be written to. Not validated: write the copy
    and ``load_scenario`` it."""
    path = scenario_file(name_or_path)
    data = _read_mapping(path)
    for key in FILE_KEYS:
        if isinstance(data.get(key), (str, list)):  # anything else: load_scenario's error
            one = isinstance(data[key], str)
            files = [(path.parent / f).resolve() for f in ([data[key]] if one else data[key])]
            files = [os.path.relpath(f, relative_to) if relative_to else str(f) for f in files]
            data[key] = files[0] if one else files
    return data


def scenario_file(name_or_path: str | Path) -> Path:
    """The YAML file of a bundled scenario's name (``env_3``) or of a path; ScenarioError for
    an unknown name or a missing file."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        candidate = scenarios_dir() / f"{name_or_path}.yaml"
        if not candidate.exists():
            raise ScenarioError(
                f"unknown scenario {str(name_or_path)!r}; available: "
                f"{', '.join(available_scenarios())} (or pass the path of a scenario .yaml file)"
            )
        path = candidate
    if not path.exists():
        raise ScenarioError(f"scenario file {path} does not exist")
    if path.is_dir():
        raise ScenarioError(f"scenario file {path} is a folder; pass the path of a scenario .yaml file")
    return path


def _read_mapping(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise ScenarioError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason}); save the "
                            "file as UTF-8") from exc
    except OSError as exc:  # unreadable: permissions, a folder, an I/O error
        raise ScenarioError(f"{path}: cannot read the scenario file ({exc.strerror or exc}); "
                            "pass a readable scenario .yaml file") from exc
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{path}: malformed YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ScenarioError(f"{path}: expected a mapping of scenario keys at the top level")
    return data


def _scenario_from_dict(data: dict[str, Any], path: Path) -> Scenario:
    base = path.parent
    data = dict(data)
    data.setdefault("name", path.stem)

    def resolve(value: Any, key: str) -> Path:
        if not isinstance(value, str):
            raise ScenarioError(f"{path}: '{key}' must be a file path string, got {value!r}")
        file = (base / value).resolve()
        if not file.exists():
            raise ScenarioError(f"{path}: '{key}' names {value!r}, which does not exist ({file})")
        return file

    def resolve_list(key: str) -> tuple[Path, ...]:
        value = data.get(key, [])
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, list):
            raise ScenarioError(f"{path}: '{key}' must be a list of file paths")
        return tuple(resolve(v, key) for v in value)

    if "net" not in data:
        raise ScenarioError(f"{path}: missing required key 'net' (the .net.xml file)")
    data["net"] = resolve(data["net"], "net")
    data["demand"] = resolve_list("demand")
    data["pedestrian_demand"] = resolve_list("pedestrian_demand")
    data["additional"] = resolve_list("additional")
    nested = {
        "region": Region,
        "background": Background,
        "reward": RewardWeights,
        "contact": Contact,
        "termination": Termination,
        "spawn_jitter": SpawnJitter,
    }
    for key, cls in nested.items():
        if key in data:
            data[key] = _build(cls, data[key], f"{path}: '{key}'")
    if "vehicle" in data:
        data["vehicle"] = _vehicle(data["vehicle"], f"{path}: 'vehicle'")
    if "region" not in data:
        raise ScenarioError(f"{path}: missing required key 'region' (center and size in metres)")
    acs = data.get("acs")
    if not isinstance(acs, list) or not acs:
        raise ScenarioError(f"{path}: 'acs' must be a non-empty list of learning-car entries")
    data["acs"] = tuple(_build(ACSpec, ac, f"{path}: acs[{i}]") for i, ac in enumerate(acs))
    data["source"] = path
    return _build(Scenario, data, str(path))


def _vehicle(data: Any, where: str) -> VehicleParams:
    """A ``vehicle:`` block: VehicleParams fields by name, angles in degrees, grip ``null``/off."""
    if not isinstance(data, dict):
        raise ScenarioError(f"{where}: expected a mapping of VehicleParams fields, got "
                            f"{type(data).__name__}")
    names = [f.name for f in dataclasses.fields(VehicleParams)]
    unknown = sorted(set(data) - set(names), key=str)
    if unknown:
        raise ScenarioError(f"{where}: unknown key(s) {unknown}; valid keys: {sorted(names)} "
                            f"({', '.join(VEHICLE_ANGLES)} in degrees, the rest in SI units)")
    kwargs = {}
    for key, value in data.items():
        if key == "max_lateral_accel" and value in GRIP_OFF:
            kwargs[key] = math.inf
            continue
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not number or not math.isfinite(value) or value <= 0:
            grip = " (or null / off: no grip limit)" if key == "max_lateral_accel" else ""
            raise ScenarioError(f"{where}: '{key}' must be a finite number > 0{grip}, got {value!r}")
        if key in VEHICLE_ANGLES:
            if key == "max_steer" and value >= 90:
                raise ScenarioError(f"{where}: 'max_steer' must be below 90 degrees, got {value!r}")
            value = math.radians(value)
        kwargs[key] = float(value)
    try:
        return VehicleParams(**kwargs)
    except ValueError as exc:
        raise ScenarioError(f"{where}: {exc}") from exc


def _build(cls: type, data: Any, where: str) -> Any:
    """Build a frozen dataclass from a mapping, rejecting unknown keys and bad values."""
    if not isinstance(data, dict):
        raise ScenarioError(f"{where}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields), key=str)  # a YAML key may be a number
    if unknown:
        raise ScenarioError(
            f"{where}: unknown key(s) {unknown}; valid keys: {sorted(fields)}"
        )
    kwargs = {}
    for key, value in data.items():
        ftype = str(fields[key].type)
        if ftype.startswith(("tuple[float", "tuple[str")) and not isinstance(value, list):
            example = f"[{value}]" if isinstance(value, str) else "[a, b]"
            raise ScenarioError(f"{where}: '{key}' must be a list, got {value!r}; write it as {example}")
        if ftype.startswith("tuple[float"):
            bad = [v for v in value if isinstance(v, bool) or not isinstance(v, int | float)]
            if bad:
                raise ScenarioError(f"{where}: '{key}' must be a list of numbers, got {value!r} "
                                    f"({bad[0]!r} is not a number)")
            value = tuple(float(v) for v in value)
        elif ftype.startswith("tuple[str"):
            value = tuple(str(v) for v in value)
        elif ftype == "float" and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if ftype in ("float", "int", "bool") and not _type_ok(value, ftype):
            raise ScenarioError(f"{where}: '{key}' must be {ftype}, got {value!r}")
        if ftype == "str" and not isinstance(value, str):  # a list or mapping would not hash
            raise ScenarioError(f"{where}: '{key}' must be text, got {value!r}; write it as "
                                f"{key}: \"...\"")
        if ftype == "float" and not math.isfinite(value):
            raise ScenarioError(f"{where}: '{key}' must be finite, got {value!r}")
        kwargs[key] = value
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ScenarioError(f"{where}: {exc}") from exc


def _type_ok(value: Any, ftype: str) -> bool:
    if ftype == "bool":
        return isinstance(value, bool)
    if ftype == "int":
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, float)
