"""cosim_v5: the multi-agent urban driving environment (PettingZoo ParallelEnv).

Agents
    ``ac_0`` .. ``ac_{N-1}``: learning cars (ACs), N = 1..6 (``num_agents``), fixed
    at construction. A finished agent leaves ``agents`` and never comes back in
    the episode; the episode ends when every agent is done.
Observation (per agent)
    ``Box(0, 255, (S, S, 3), uint8)``: RGB image of a forward camera at the car's
    windshield, ~90 degree field of view, S = ``image_size`` (default 84),
    rendered by the PyBullet mirror of the SUMO world. ``parallel_env(frame_stack=K)``
    stacks the last K (``cosim train`` trains on K = 4; docs/task.md, "Observation").
    ``camera=False`` (``parallel_env(obs="state")``): the state track, ``Box((65,), float32)``
    per agent (cosim.state: speed, route geometry, goal, previous control, next signal,
    nearest vehicles and pedestrians), and no PyBullet mirror is built or rendered.
    ``draw_route`` (``parallel_env(obs="route")``): the camera frame of each AC named (True:
    every AC) shows its own route's next 40 m as a magenta band on the ground (the route camera,
    cosim.mirror.RouteBand; docs/task.md, "The route variant").
Action (per agent, mixed in one env)
    ``Discrete(9)``: the paper's (throttle/brake, steer) table (SPEC §2), or
    ``Box(-1, 1, (2,), float32)``: (throttle(+)/brake(-), steer). No reverse.
Reward (per agent, per step; weights from the scenario YAML)
    collision (-50 once per collision event with a car, object or pedestrian: one event per
    other actor, the same one again within 5 s being the same event; a car contact only for the
    car at fault, ``collision_fault="both"`` charges both, task version 4;
    ``collision_charge="step"`` charges every contact step, task version 3; docs/task.md,
    "Collision rule")
    + efficiency (10 * (metres gained towards the goal + speed / speed limit), the speed term
    only on new ground: a step nearer the goal than the AC has been)
    + lane (-0.5 per step off the road or outside its lanes) + step (-1).
    Each weighted term is in ``infos[agent]["reward_terms"]``.
Termination
    goal reached, leaving the region; truncation at ``horizon`` steps. A collision
    does not end the episode (the test's rule, the default for training too: each
    collision event is charged once, and a car or object the AC drives into stops it where it
    was); ``terminate_on_collision=True`` is the paper's training rule.
Infos
    every event (collision_vehicle / _pedestrian / _object: in contact this step;
    event_vehicle / _pedestrian / _object: a new collision event this step; off_road,
    wrong_lane, red_light, goal_reached, out_of_region), route_completion (0..1 so far),
    distance_to_goal, progress, speed, x, y,
    heading, reward_terms, n_vehicles and n_pedestrians (others in the region),
    spawn_x/y, goal_x/y, time (simulated seconds); on an agent's last step also
    ``cosim_episode`` (not ``episode``, which Gymnasium's RecordEpisodeStatistics,
    ``gym.make_vec`` and SB3's Monitor write): its unscaled return, length, sum of
    each reward term (r_*), count of steps with each event (n_*), mean speed,
    DISTANCE, whether it reached the goal, route_completion, infraction_penalty,
    driving_score and success (goal with no infraction; cosim/score.py).
Arguments
    scenario (name like ``env_3`` or a YAML path), num_agents, action_types
    ("discrete", "continuous", or one per agent), seed, image_size, background,
    pedestrians, terminate_on_collision, horizon, renderer ("tiny", "egl",
    "auto"), render_mode ("rgb_array"), backend ("auto", "libsumo", "traci"),
    collision_charge ("event" or "step": overrides the scenario's Contact.charge),
    collision_fault ("at_fault" or "both": overrides the scenario's Contact.fault),
    camera (default True; False: the state track, no PyBullet mirror; see Observation),
    draw_route (default False; True or AC ids: the route camera of those ACs; see Observation),
    reward_scale (> 0, default 1.0: multiplies the returned rewards; reward_terms
    and ``cosim_episode`` stay unscaled), stall_truncate (a training option: truncate
    every AC's episode once all have stood still that many steps; Termination.stall_truncate).
Pickling
    ``pickle`` and ``copy.deepcopy`` rebuild the environment from its constructor
    arguments (SUMO and PyBullet state cannot be copied): the copy starts un-reset.
Version history
    The id's suffix is ``cosim.TASK_VERSION``: v5 (2026-12-02) charges a vehicle contact only
    to the car at fault and pays the speed term only on new ground; v4 (2026-12-01) charges a contact once per collision event, makes cars
    ahead solid, has traffic see ACs off their lanes and adds the driving score; v0 was the name
    of task versions 1-3 (see ``cosim.TASK_VERSION``).
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
import time
from collections.abc import Mapping, Sequence

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from cosim.dynamics import action_to_control
from cosim.errors import ActionError, EnvStateError, OptionError, ScenarioError
from cosim.events import EVENT_FLAGS
from cosim.scenario import CONTACT_CHARGES, CONTACT_FAULTS, Scenario, load_scenario
from cosim.score import episode_score
from cosim.state import state_space as _state_space
from cosim.state import state_vectors
from cosim.version import TASK_VERSION
from cosim.world import World

log = logging.getLogger(__name__)

ACTION_TYPES = ("discrete", "continuous")
EPISODE_INFO = "cosim_episode"  # the info key of an agent's per-episode summary
# the events counted in an agent's per-episode summary (steps with that event)
EPISODE_EVENTS = (*(e for e in EVENT_FLAGS if e not in ("goal_reached", "out_of_region")),
                  "lane_violation")


class CosimParallelEnv(ParallelEnv):
    """See the module docstring (the spec card)."""

    metadata = {"name": f"cosim_v{TASK_VERSION}", "render_modes": ["rgb_array"], "render_fps": 10,
                "is_parallelizable": True}

    def __init__(
        self,
        scenario: str | Scenario = "env_3",
        num_agents: int | None = None,
        action_types: str | Sequence[str] | Mapping[str, str] = "discrete",
        seed: int | None = None,
        image_size: int = 84,
        background: bool = True,
        pedestrians: bool = True,
        terminate_on_collision: bool | None = None,
        horizon: int | None = None,
        renderer: str = "tiny",
        render_mode: str | None = None,
        backend: str = "auto",
        reward_scale: float = 1.0,
        stall_truncate: int | None = None,
        collision_charge: str | None = None,
        collision_fault: str | None = None,
        camera: bool = True,
        draw_route: bool | Sequence[str] = False,
    ):
        # everything pickle / deepcopy need to rebuild this env (see __getstate__)
        self._init_kwargs = {k: v for k, v in locals().items() if k not in ("self", "__class__")}
        _check_seed(seed, "parallel_env(seed=...)")
        if not (isinstance(reward_scale, int | float) and 0.0 < float(reward_scale) < float("inf")):
            raise ValueError(f"reward_scale must be a finite number > 0, got {reward_scale!r}")
        sc = load_scenario(scenario) if not isinstance(scenario, Scenario) else scenario
        if terminate_on_collision is not None:
            sc = sc.with_overrides(
                termination=dataclasses.replace(sc.termination, on_collision=terminate_on_collision)
            )
        if horizon is not None:
            sc = sc.with_overrides(horizon=int(horizon))
        if collision_charge is not None:  # Contact.charge: "event" (the default) or "step"
            if collision_charge not in CONTACT_CHARGES:
                raise ValueError(f"collision_charge must be one of {', '.join(CONTACT_CHARGES)}, "
                                 f"got {collision_charge!r}")
            sc = sc.with_overrides(contact=dataclasses.replace(sc.contact, charge=collision_charge))
        if collision_fault is not None:  # Contact.fault: "at_fault" (the default) or "both"
            if collision_fault not in CONTACT_FAULTS:
                raise ValueError(f"collision_fault must be one of {', '.join(CONTACT_FAULTS)}, "
                                 f"got {collision_fault!r}")
            sc = sc.with_overrides(contact=dataclasses.replace(sc.contact, fault=collision_fault))
        if stall_truncate is not None:  # a training option (Termination.stall_truncate)
            sc = sc.with_overrides(
                termination=dataclasses.replace(sc.termination, stall_truncate=stall_truncate)
            )
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if not 8 <= int(image_size) <= 512:
            raise ValueError(f"image_size must be 8..512 pixels, got {image_size}")
        self.scenario = sc
        self.reward_scale = float(reward_scale)
        self.render_mode = render_mode
        self.image_size = int(image_size)
        self._renderer = renderer
        self._background = background
        self._pedestrians = pedestrians
        self._world = World(sc, num_agents, background=background, pedestrians=pedestrians,
                            backend=backend)
        self.possible_agents = list(self._world.ac_ids)
        self.agents: list[str] = []
        self.action_types = _resolve_action_types(action_types, self.possible_agents)
        self._camera = bool(camera)
        self._obs_space = (spaces.Box(0, 255, (self.image_size, self.image_size, 3), np.uint8)
                           if self._camera else _state_space())
        self._last_controls: dict[str, tuple[float, float]] = {}
        self._action_spaces = {
            a: spaces.Discrete(9) if t == "discrete" else spaces.Box(-1.0, 1.0, (2,), np.float32)
            for a, t in self.action_types.items()
        }
        self._rng = np.random.default_rng(seed)
        self._route_agents: frozenset[str] = frozenset()
        self.draw_routes(draw_route)
        self._mirror = None
        self._closed = False
        self._needs_reset = True
        self._episode: dict[str, dict] = {}
        self._last_infos: dict[str, dict] = {}
        self.timings = {"sumo_world": 0.0, "mirror_sync": 0.0, "render": 0.0, "steps": 0}

    # -- spaces (the same object every call, as PettingZoo requires) ----------
    def observation_space(self, agent: str) -> spaces.Box:
        self._check_agent(agent)
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Space:
        self._check_agent(agent)
        return self._action_spaces[agent]

    # -- lifecycle -----------------------------------------------------------
    def reset(self, seed: int | None = None, options: dict | None = None):
        if self._closed:
            raise EnvStateError("the environment is closed; create a new one")
        _check_seed(seed, "reset(seed=...)")
        options = options or {}
        _check_reset_options(options)
        # these two take effect at this reset and stay until changed again
        bridge = self._world.bridge
        if "background" in options:
            bridge.background = bool(options["background"]) and self.scenario.background.enabled
        if "pedestrians" in options:
            bridge.pedestrians = bool(options["pedestrians"]) and self.scenario.pedestrians
        if seed is not None:
            self._rng = np.random.default_rng(seed)
            for i, a in enumerate(self.possible_agents):
                self._action_spaces[a].seed(int(seed) + i)
        sumo_seed = int(seed) if seed is not None else int(self._rng.integers(0, 2**31 - 1))
        results = self._world.reset(seed=sumo_seed)
        if self._mirror is None and self._camera:
            self._mirror = self._make_mirror()
        self._last_controls = {}
        self.agents = list(self._world.active)
        self._episode: dict[str, dict] = {}
        self._needs_reset = False
        obs = self._observe(self.agents)
        infos = {a: self._info(a, results[a]) for a in self.agents}
        self._last_infos = infos
        return obs, infos

    def step(self, actions: Mapping[str, object]):
        if self._closed:
            raise EnvStateError("the environment is closed; create a new one")
        if self._needs_reset:
            raise EnvStateError("step() called before reset(); call env.reset(seed=...) first")
        if not self.agents:
            raise EnvStateError("every agent is done; call env.reset() to start a new episode")
        controls = self._controls(actions)
        self._last_controls.update(controls)
        t0 = time.perf_counter()
        results = self._world.step(controls)
        t1 = time.perf_counter()
        stepped = list(results)
        obs = self._observe(stepped)
        self.agents = list(self._world.active)
        rewards = {a: r.reward * self.reward_scale for a, r in results.items()}
        terminations = {a: r.terminated for a, r in results.items()}
        truncations = {a: r.truncated for a, r in results.items()}
        infos = {a: self._info(a, r) for a, r in results.items()}
        for a, r in results.items():
            self._accumulate(a, r, infos[a])
        self._last_infos = infos
        self.timings["sumo_world"] += t1 - t0
        self.timings["steps"] += 1
        return obs, rewards, terminations, truncations, infos

    def render(self):
        """An RGB overview of the region (top-down), for ``render_mode="rgb_array"``."""
        if self.render_mode is None:
            log.warning("render() called with render_mode=None; pass render_mode='rgb_array'")
            return None
        if self._needs_reset or self._world.snapshot is None:
            raise EnvStateError("render() called before reset()")
        if not self._camera:  # the state track: a mirror only for this overview, built on demand
            if self._mirror is None:
                self._mirror = self._make_mirror()
            self._mirror.sync(self._world.snapshot)
        return self._mirror.overview()

    def close(self) -> None:
        """Close SUMO and PyBullet. Safe to call twice."""
        self._world.close()
        if self._mirror is not None:
            self._mirror.close()
            self._mirror = None
        self._closed = True
        self.agents = []

    def __getstate__(self) -> dict:
        """Only the constructor arguments: a copy is a new, un-reset environment."""
        return {"init_kwargs": dict(self._init_kwargs)}

    def __setstate__(self, state: dict) -> None:
        self.__init__(**state["init_kwargs"])

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: modules may already be gone
            pass

    @property
    def world(self) -> World:
        """The SUMO-side world (snapshot, routes, poses): for controllers and evaluation."""
        return self._world

    @property
    def last_infos(self) -> dict[str, dict]:
        """The infos of the last reset or step, per AC (what it returned): what a policy that
        drives one AC of a shared env reads beside its camera (eval/testing/rollout.py NavPolicy)."""
        return self._last_infos

    @property
    def last_controls(self) -> dict[str, tuple[float, float]]:
        """Each AC's (throttle/brake, steer) of the last step it took this episode (none after a
        reset): the previous control in the state vector (cosim.state.agent_state)."""
        return self._last_controls

    @property
    def camera(self) -> bool:
        """Whether the ACs observe their cameras (else their state vectors, cosim.state)."""
        return self._camera

    def cameras_off(self) -> None:
        """Switch to the state track: each AC observes its state vector (cosim.state) and no
        PyBullet mirror is built (one already built is closed). Call it before the spaces are
        read and before a reset (cosim.wrappers.observation_wrappers does, for ``obs="state"``,
        on an env built with the camera's default)."""
        self._camera = False
        self._init_kwargs["camera"] = False
        self._route_agents = frozenset()
        self._init_kwargs["draw_route"] = False
        self._obs_space = _state_space()
        if self._mirror is not None:
            self._mirror.close()
            self._mirror = None

    def draw_routes(self, agents: bool | Sequence[str] = True) -> None:
        """The route camera (``obs="route"``): each AC of ``agents`` (True: every AC, False or
        none: no AC) sees its own route ahead drawn on the ground of its own camera frame
        (cosim.mirror.RouteBand; docs/task.md, "The route variant"); the others see the plain
        camera. Takes effect at the next observation; a copy of the env keeps it."""
        if isinstance(agents, str):
            agents = [agents]
        chosen = list(self.possible_agents) if agents is True else [] if agents is False else list(agents)
        unknown = [a for a in chosen if a not in self.possible_agents]
        if unknown:
            raise ValueError(f"draw_route: unknown agent id(s) {unknown}; the agents are {self.possible_agents}")
        if chosen and not self._camera:
            raise ValueError("draw_route draws the route into the AC cameras, which are off (camera=False, "
                             "the state track); use obs='route' with the cameras on")
        self._route_agents = frozenset(chosen)
        self._init_kwargs["draw_route"] = agents if isinstance(agents, bool) else list(chosen)

    @property
    def route_agents(self) -> frozenset[str]:
        """The ACs whose camera frames show their own route ahead (:meth:`draw_routes`)."""
        return self._route_agents

    @property
    def mirror(self):
        return self._mirror

    # -- internals -----------------------------------------------------------
    def _make_mirror(self):
        from cosim.mirror import Mirror

        return Mirror(self._world.roadmap, image_size=self.image_size, renderer=self._renderer)

    def _observe(self, agents: list[str]) -> dict[str, np.ndarray]:
        if not agents:
            return {}
        if not self._camera:
            t0 = time.perf_counter()
            states = state_vectors(self._world, agents, self._last_controls)
            self.timings["state"] = self.timings.get("state", 0.0) + time.perf_counter() - t0
            return {a: states[i] for i, a in enumerate(agents)}
        t0 = time.perf_counter()
        self._mirror.sync(self._world.snapshot)
        t1 = time.perf_counter()
        poses = [self._world.ac_state(a)[:3] for a in agents]
        images = self._mirror.cameras(poses, self._routes_ahead(agents, poses))
        self.timings["mirror_sync"] += t1 - t0
        self.timings["render"] += time.perf_counter() - t1
        return {a: images[i] for i, a in enumerate(agents)}

    def _routes_ahead(self, agents: list[str], poses) -> list | None:
        """Each route-camera AC's own route ahead (cosim.roadmap.Route.ahead), None for the others."""
        if not self._route_agents:
            return None
        from cosim.mirror import ROUTE_AHEAD, ROUTE_SPACING

        return [self._world.route(a).ahead(x, y, ROUTE_AHEAD, ROUTE_SPACING) if a in self._route_agents
                else None for a, (x, y, _) in zip(agents, poses, strict=True)]

    def _controls(self, actions: Mapping[str, object]) -> dict[str, tuple[float, float]]:
        if not isinstance(actions, Mapping):
            raise ActionError(
                f"actions must be a dict {{agent: action}} for agents {self.agents}, "
                f"got {type(actions).__name__}"
            )
        unknown = [a for a in actions if a not in self.agents]
        if unknown:
            done = [a for a in unknown if a in self.possible_agents]
            why = f"{done} already finished this episode" if done else "unknown agent id(s)"
            raise ActionError(
                f"actions for {unknown}: {why}; the active agents are {self.agents}"
            )
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ActionError(f"no action for active agent(s) {missing}; give one for each of {self.agents}")
        controls = {}
        for a in self.agents:
            try:
                controls[a] = action_to_control(
                    actions[a], self.action_types[a] == "discrete", a, self._world.vehicle
                )
            except ActionError as exc:
                raise ActionError(f"{exc} (expected space: {self._action_spaces[a]})") from None
        return controls

    def _info(self, agent: str, result) -> dict:
        """The world's per-AC info plus what metrics need: who else is around, spawn, goal."""
        info = result.info()
        snap = self._world.snapshot
        route = self._world.route(agent)
        info["n_vehicles"] = len(snap.vehicle_ids) - 1  # every other car, ACs included
        info["n_pedestrians"] = len(snap.person_ids)
        info["spawn_x"], info["spawn_y"] = (float(v) for v in route.spawn_xy)
        info["goal_x"], info["goal_y"] = route.goal_point
        info["time"] = float(snap.time)
        return info

    def _accumulate(self, agent: str, result, info: dict) -> None:
        """Per-episode sums (unscaled); the agent's last info gets them as ``info[EPISODE_INFO]``."""
        ep = self._episode.setdefault(agent, {"return": 0.0, "length": 0, "speed_sum": 0.0})
        ep["return"] += result.reward
        ep["length"] += 1
        ep["speed_sum"] += info["speed"]
        for term, value in result.reward_terms.items():
            ep[f"r_{term}"] = ep.get(f"r_{term}", 0.0) + value
        for key in EPISODE_EVENTS:
            ep[f"n_{key}"] = ep.get(f"n_{key}", 0) + int(bool(info[key]))
        if result.terminated or result.truncated:
            ep = self._episode.pop(agent)
            ep["mean_speed_kmh"] = 3.6 * ep.pop("speed_sum") / ep["length"]
            ep["goal_reached"] = bool(info["goal_reached"])
            ep["distance_to_goal"] = info["distance_to_goal"]
            gx, gy, sx, sy = info["goal_x"], info["goal_y"], info["spawn_x"], info["spawn_y"]
            ep["DISTANCE"] = float(np.hypot(gx - sx, gy - sy) - np.hypot(gx - info["x"], gy - info["y"]))
            # the driving score (cosim/score.py; docs/task.md, "Driving score")
            score = episode_score(info["route_completion"], ep["goal_reached"], ep["n_event_vehicle"],
                                  ep["n_event_pedestrian"], ep["n_event_object"], ep["n_red_light"])
            ep["route_completion"] = float(info["route_completion"])
            ep["infraction_penalty"] = score["IP"]
            ep["driving_score"] = score["DS"]
            ep["success"] = bool(score["success"])
            info[EPISODE_INFO] = ep

    def _check_agent(self, agent: str) -> None:
        if agent not in self._action_spaces:
            raise KeyError(f"unknown agent {agent!r}; the agents are {self.possible_agents}")


RESET_OPTIONS = ("background", "pedestrians")


def _check_seed(seed, where: str) -> None:
    """Refuse a seed numpy and SUMO cannot take (Gymnasium's rule: None or a whole number >= 0)."""
    whole = isinstance(seed, int | np.integer) and not isinstance(seed, bool)
    if seed is not None and not (whole and seed >= 0):
        raise OptionError(f"{where}: the seed must be a whole number >= 0 (or None: a fresh one), "
                          f"got {seed!r}")


def _check_reset_options(options) -> None:
    """Refuse a misspelt reset option (``backgrund``) naming the valid keys.

    A key close to no valid one is ignored with a warning rather than refused:
    PettingZoo's own API test resets with ``options={"options": 1}``.
    """
    if not isinstance(options, Mapping):
        raise OptionError(f"reset(options=...) must be a dict, got {options!r}; valid keys: "
                          f"{list(RESET_OPTIONS)}")
    for key in options:
        if key in RESET_OPTIONS:
            continue
        close = difflib.get_close_matches(str(key).lower(), RESET_OPTIONS, n=1, cutoff=0.6)
        if close:
            raise OptionError(f"reset(options=...): unknown option {key!r}, did you mean {close[0]!r}? "
                              f"valid keys: {list(RESET_OPTIONS)}")
        log.warning("reset(options=...): ignoring unknown option %r; valid keys: %s", key,
                    list(RESET_OPTIONS))


def _resolve_action_types(action_types, agents: list[str]) -> dict[str, str]:
    if isinstance(action_types, str):
        types = dict.fromkeys(agents, action_types)
    elif isinstance(action_types, Mapping):
        missing = [a for a in agents if a not in action_types]
        if missing:
            raise ScenarioError(f"action_types has no entry for {missing}")
        types = {a: action_types[a] for a in agents}
    else:
        action_types = list(action_types)
        if len(action_types) != len(agents):
            raise ScenarioError(
                f"action_types lists {len(action_types)} types for {len(agents)} agents"
            )
        types = dict(zip(agents, action_types, strict=True))
    bad = {a: t for a, t in types.items() if t not in ACTION_TYPES}
    if bad:
        raise ScenarioError(f"unknown action type(s) {bad}; valid: {list(ACTION_TYPES)}")
    return types


def parallel_env(scenario: str | Scenario = "env_3", frame_stack: int = 1, obs: str = "image", **kwargs):
    """The multi-agent environment (PettingZoo ParallelEnv); see :mod:`cosim.env`.

    ``frame_stack`` K > 1 gives each AC its last K camera frames (cosim.wrappers.FrameStack),
    the observation ``cosim train`` uses by default (K = 4); ``obs="nav"`` adds the
    measurements vector beside them in a Dict (cosim.wrappers.NavObservation; docs/task.md,
    "Observation"); ``obs="state"`` is the state track: a 65-number vector per AC and the
    cameras off (``CosimParallelEnv(camera=False)``, cosim.state; frame_stack must be 1);
    ``obs="route"``: the camera frames with each AC's own route ahead drawn on the ground
    (``CosimParallelEnv.draw_routes``; docs/task.md, "The route variant").
    """
    from cosim.wrappers import (
        check_frame_stack,
        check_obs_variant,
        check_state_stack,
        observation_wrappers,
    )

    check_frame_stack(frame_stack)  # before SUMO and PyBullet are set up
    check_obs_variant(obs)
    check_state_stack(obs, frame_stack)
    if obs == "state":
        kwargs.setdefault("camera", False)
    return observation_wrappers(CosimParallelEnv(scenario, **kwargs), frame_stack=frame_stack, obs=obs)
