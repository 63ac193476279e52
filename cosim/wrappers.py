"""ParallelEnv wrappers: frame stacking (:class:`FrameStack`, :class:`FrameHistory`), the
``nav`` observation (:class:`NavObservation`: image and measurements), the ``state`` track
(cameras off, cosim.state), the ``route`` camera (the env draws it), action repeat
(:class:`ActionRepeat`), and :class:`BlackDeath` for libraries that need every agent present
at every step. :func:`observation_wrappers` builds an AC's observation from these
(docs/task.md, "Observation" and "Action repeat").

A single camera frame has no velocity. :class:`FrameStack` gives each agent its last K
frames, stacked on the channel axis oldest first (84x84x3 -> 84x84x3K); at a reset the
history is K copies of the first frame. :class:`FrameHistory` is the stack of one camera,
which a policy that drives one car of a shared test environment keeps for itself
(eval/testing/rollout.py ``StackedPolicy``), so training and testing stack identically.

SuperSuit's ``pettingzoo_env_to_vec_env_v1`` (and SB3 or CleanRL behind it) makes each
agent one slot of a vector env, so every agent must appear in every step's output
until the whole episode ends. SuperSuit's own ``black_death_v3`` (3.11) ends the
episode only when every agent is terminated *and* truncated, which never happens in
cosim (an AC that reaches its goal is terminated, not truncated), so it steps an
environment with no agents left. :class:`BlackDeath` is the same idea with the
episode ending when every agent has finished.
"""

from __future__ import annotations

import gymnasium
import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper


class FrameHistory:
    """The last ``k`` frames of one camera, concatenated on the last axis, oldest first.

    :meth:`push` adds a frame and returns the stack (a new array); the first push after
    construction or :meth:`clear` fills all ``k`` slots with that frame.
    """

    def __init__(self, k: int):
        if int(k) < 1:
            raise ValueError(f"a frame stack needs k >= 1 frames, got {k}")
        self.k = int(k)
        self.stack: np.ndarray | None = None

    def clear(self) -> None:
        """Forget the frames (an episode boundary): the next push starts a new stack."""
        self.stack = None

    def push(self, frame: np.ndarray) -> np.ndarray:
        frame = np.asarray(frame)
        if self.stack is None:
            self.stack = np.concatenate([frame] * self.k, axis=-1)
        else:
            self.stack = np.concatenate([self.stack[..., frame.shape[-1]:], frame], axis=-1)
        return self.stack


def stacked_space(space: gymnasium.spaces.Box, k: int) -> gymnasium.spaces.Box:
    """The observation space of ``k`` stacked frames of ``space`` (channels-last)."""
    return gymnasium.spaces.Box(np.concatenate([space.low] * k, axis=-1),
                                np.concatenate([space.high] * k, axis=-1), dtype=space.dtype)


class _Forwarding(BaseParallelWrapper):
    """A ParallelEnv wrapper whose agents and spaces are the wrapped env's unless it says
    otherwise (the properties BaseParallelWrapper leaves to ``__getattr__``)."""

    @property
    def agents(self) -> list:
        return self.env.agents

    @property
    def possible_agents(self) -> list:
        return self.env.possible_agents

    def observation_space(self, agent):
        return self.env.observation_space(agent)

    def action_space(self, agent):
        return self.env.action_space(agent)


class FrameStack(_Forwarding):
    """Each agent observes its last ``k`` camera frames, stacked oldest first (84x84x3k).

    ``reset`` starts every agent's history with ``k`` copies of its first frame; ``step``
    pushes each returned observation, the final one of an agent that finishes included,
    so a transition's next observation is the stack the agent would see next. ``k = 1``
    returns the frames unchanged.
    """

    def __init__(self, env, k: int):
        super().__init__(env)
        self.k = int(k)
        if self.k < 1:
            raise ValueError(f"FrameStack needs k >= 1 frames, got {k}")
        self._spaces = {a: stacked_space(env.observation_space(a), self.k) for a in env.possible_agents}
        self._history = {a: FrameHistory(self.k) for a in env.possible_agents}

    def observation_space(self, agent):
        return self._spaces[agent]

    def reset(self, seed=None, options=None):
        obs, infos = self.env.reset(seed=seed, options=options)
        for history in self._history.values():
            history.clear()
        return self._push(obs), infos

    def step(self, actions):
        obs, rewards, terms, truncs, infos = self.env.step(actions)
        return self._push(obs), rewards, terms, truncs, infos

    def _push(self, obs: dict) -> dict:
        return {a: self._history[a].push(o) for a, o in obs.items()}


class ActionRepeat(_Forwarding):
    """Each agent's action is held for ``k`` environment steps: one ``step`` of this wrapper
    is up to ``k`` steps of ``env`` (docs/task.md, "Action repeat").

    An agent's reward is the sum of its rewards over the steps it took; an agent that finishes
    (goal, region left, horizon) at an inner step takes no more of them, and its observation,
    termination, truncation and info are those of that step; the wrapper stops early when no
    agent is left. The others get the last inner step's. ``k = 1`` is ``env`` itself. The test
    drives a checkpoint trained through this wrapper by holding its actions itself
    (eval/testing/rollout.py ``RepeatPolicy``), which gives the same episode.
    """

    def __init__(self, env, k: int):
        super().__init__(env)
        self.k = check_action_repeat(k)

    def step(self, actions):
        obs, rewards, terms, truncs, infos = {}, {a: 0.0 for a in actions}, {}, {}, {}
        live = dict(actions)
        for _ in range(self.k):
            o, r, te, tr, inf = self.env.step(live)
            for a, v in r.items():
                rewards[a] = rewards.get(a, 0.0) + float(v)
            obs.update(o)
            terms.update(te)
            truncs.update(tr)
            infos.update(inf)
            left = set(self.env.agents)
            live = {a: act for a, act in live.items() if a in left}
            if not live:
                break
        return obs, rewards, terms, truncs, infos


def check_action_repeat(k) -> int:
    """``k`` as an int >= 1, or a ValueError naming it."""
    if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
        raise ValueError(f"action_repeat must be a whole number of environment steps >= 1 (1: an action "
                         f"every step), got {k!r}")
    return int(k)


OBS_VARIANTS = ("image", "nav", "state", "route")
"""What an AC observes: its camera frames ("image"), those beside a measurements vector
("nav": :class:`NavObservation`), with the cameras off its state vector ("state": the
state track, cosim.state; ``CosimParallelEnv(camera=False)``), or its camera frames with its
own route ahead drawn on the ground ("route": the route camera,
``CosimParallelEnv.draw_routes``, cosim.mirror.RouteBand; the same space as "image")."""


def observation_wrappers(env, frame_stack: int = 1, obs: str = "image", action_repeat: int = 1):
    """``env`` with the observation a run trains on: its last ``frame_stack`` camera frames
    (:class:`FrameStack`; 1 leaves the camera as it is) and, with ``obs="nav"``, the
    measurements beside them (:class:`NavObservation`); with ``action_repeat`` R > 1 each
    action held for R steps (:class:`ActionRepeat`, innermost: the frames stacked are those
    the agent decided on). With ``obs="state"`` the env's cameras are switched off
    (``CosimParallelEnv.cameras_off``, before its first reset: no PyBullet mirror) and each AC
    observes its state vector (cosim.state); ``frame_stack`` must then be 1. With
    ``obs="route"`` every AC's camera frame shows its own route ahead
    (``CosimParallelEnv.draw_routes``), stacked like "image". The one place the
    training, validation and library factories build an AC's observation (docs/task.md,
    "Observation")."""
    k = check_frame_stack(frame_stack)
    check_obs_variant(obs)
    check_state_stack(obs, k)
    repeat = check_action_repeat(action_repeat)
    if obs == "state" and env.unwrapped.camera:
        env.unwrapped.cameras_off()
    if obs == "route":
        env.unwrapped.draw_routes(True)
    env = ActionRepeat(env, repeat) if repeat > 1 else env
    env = FrameStack(env, k) if k > 1 else env
    return NavObservation(env) if obs == "nav" else env


def check_obs_variant(obs) -> str:
    """``obs`` if it names an observation variant, else a ValueError listing them."""
    if obs not in OBS_VARIANTS:
        raise ValueError(f"obs must be one of {', '.join(OBS_VARIANTS)}, got {obs!r}")
    return obs


def check_state_stack(obs: str, frame_stack: int) -> None:
    """Refuse a frame stack K > 1 with ``obs="state"``: K stacks camera frames, which give a
    single image its missing velocity; the state vector has the speeds already (the AC's and its
    neighbours' relative velocities), so the state track observes one vector."""
    if obs == "state" and int(frame_stack) != 1:
        raise ValueError(f"frame_stack={frame_stack} stacks camera frames; obs='state' observes one state "
                         "vector (it carries the speeds): use frame_stack=1 (--frame-stack 1) with it")


def check_frame_stack(frame_stack) -> int:
    """``frame_stack`` as an int >= 1, or a ValueError naming it."""
    if isinstance(frame_stack, bool) or not isinstance(frame_stack, int | np.integer) or frame_stack < 1:
        raise ValueError(f"frame_stack must be an int >= 1 (1: a single camera frame), got {frame_stack!r}")
    return int(frame_stack)


NAV_COMMANDS = ("follow", "left", "straight", "right", "u-turn")
"""The route command of the ``nav`` observation, one-hot in this order. "follow": keep the
lane (far from the junction, or past it); the others: the route's movement through its
junction (cosim.roadmap.movement; through a roundabout the heading change between entry and
exit, so the bundled four-arm roundabout's first, second and third exits read right,
straight and left: the command names the exit)."""
NAV_SWITCH_DISTANCE = 50.0
"""Metres of route before the junction (the end of the first edge: its stop line) from which
the command names the movement: about 3.6 s at the 13.9 m/s speed limit, enough to pick the
lane and slow for a turn. The bundled junction scenarios spawn their ACs 25 or 45 m before
the junction, so each starts with its command; the Merge's ACs (59-103 m) drive up to ~50 m
under "follow" first (docs/task.md, "Observation")."""
NAV_SPEED_SCALE = 13.89
"""m/s that read as 1.0 in the speed measurement (the scenarios' speed limit)."""
NAV_MAX_SPEED = 25.0
"""The learning car's top speed (cosim.dynamics.VehicleParams.max_speed): the bound of the
speed measurement's space, NAV_MAX_SPEED / NAV_SPEED_SCALE."""


def nav_command(s: float, entry_s: float, exit_s: float, movement: str,
                switch_distance: float = NAV_SWITCH_DISTANCE) -> str:
    """The route command at arc length ``s``: the movement from ``switch_distance`` metres
    before the junction entry ``entry_s`` until its exit ``exit_s``, "follow" elsewhere (and
    on a route without a junction, ``entry_s`` >= ``exit_s``)."""
    if movement not in NAV_COMMANDS or movement == "follow":
        raise ValueError(f"movement must be one of {', '.join(NAV_COMMANDS[1:])}, got {movement!r}")
    if entry_s >= exit_s:
        return "follow"
    return movement if entry_s - switch_distance <= s < exit_s else "follow"


def nav_measurements(speed: float, distance_to_goal: float, route_length: float, command: str) -> np.ndarray:
    """The ``nav`` measurements vector: forward speed / NAV_SPEED_SCALE, the command one-hot
    (NAV_COMMANDS order), distance to the goal along the route / the spawn's (0..1)."""
    onehot = [float(command == c) for c in NAV_COMMANDS]
    speed = min(max(float(speed), 0.0), NAV_MAX_SPEED) / NAV_SPEED_SCALE
    remaining = min(max(float(distance_to_goal) / max(float(route_length), 1e-6), 0.0), 1.0)
    return np.array([speed, *onehot, remaining], np.float32)


def nav_space() -> gymnasium.spaces.Box:
    """The space of :func:`nav_measurements`."""
    high = np.array([NAV_MAX_SPEED / NAV_SPEED_SCALE, *([1.0] * len(NAV_COMMANDS)), 1.0], np.float32)
    return gymnasium.spaces.Box(np.zeros_like(high), high, dtype=np.float32)


class RouteGuide:
    """The geometry :func:`nav_command` needs of one AC's route: where its junction starts
    and ends along the route, its movement and its spawn-to-goal length. Built from a cosim
    route (:meth:`of_route`) or by hand (tests)."""

    def __init__(self, entry_s: float, exit_s: float, movement: str, route_length: float, goal_s: float):
        self.entry_s, self.exit_s, self.movement = float(entry_s), float(exit_s), movement
        self.route_length, self.goal_s = float(route_length), float(goal_s)

    @classmethod
    def of_route(cls, route, net) -> RouteGuide:
        """From a cosim.roadmap.Route and the SUMO network it was read from: the junction
        begins where the first edge ends and ends where the last edge begins."""
        from cosim.roadmap import movement

        first, last = net.getEdge(route.edges[0]), net.getEdge(route.edges[-1])
        entry = first.getLength() if len(route.edges) > 1 else route.path.length
        exit_ = route.path.length - last.getLength() if len(route.edges) > 1 else route.path.length
        return cls(entry, exit_, movement(net, route.edges), route.goal_s - route.spawn_s, route.goal_s)

    @classmethod
    def of_agent(cls, env, agent: str) -> RouteGuide:
        """The guide of AC ``agent``'s route in a cosim env (or a wrapper of one)."""
        world = env.unwrapped.world
        return cls.of_route(world.route(agent), world.roadmap.net)

    def command(self, distance_to_goal: float) -> str:
        """The command where the car is, given its distance to the goal along the route."""
        return nav_command(self.goal_s - float(distance_to_goal), self.entry_s, self.exit_s, self.movement)

    def measurements(self, speed: float, distance_to_goal: float) -> np.ndarray:
        return nav_measurements(speed, distance_to_goal, self.route_length, self.command(distance_to_goal))

    def observe(self, image, info: dict) -> dict:
        """The ``nav`` observation of the AC: ``image`` beside the measurements read from the info
        of the same step (its speed and distance to the goal)."""
        return {"image": image, "measurements": self.measurements(info["speed"], info["distance_to_goal"])}


class NavObservation(_Forwarding):
    """The ``nav`` observation: ``Dict(image=<the camera frames>, measurements=Box(7))``.

    The measurements (:func:`nav_measurements`) are forward speed, the route command one-hot
    (:data:`NAV_COMMANDS`, switched on :data:`NAV_SWITCH_DISTANCE` metres before the
    junction) and the remaining distance to the goal, read from the same step's info (speed,
    distance_to_goal) and the AC's route: what macad-gym's ``send_measurements`` gave and
    the paper left off (docs/task.md, "Observation").
    """

    def __init__(self, env):
        super().__init__(env)
        self._spaces = {a: gymnasium.spaces.Dict({"image": env.observation_space(a),
                                                  "measurements": nav_space()})
                        for a in env.possible_agents}
        self._guides: dict[str, RouteGuide] | None = None

    def observation_space(self, agent):
        return self._spaces[agent]

    def reset(self, seed=None, options=None):
        obs, infos = self.env.reset(seed=seed, options=options)
        if self._guides is None:
            self._guides = {a: RouteGuide.of_agent(self.env, a) for a in self.possible_agents}
        return self._join(obs, infos), infos

    def step(self, actions):
        obs, rewards, terms, truncs, infos = self.env.step(actions)
        return self._join(obs, infos), rewards, terms, truncs, infos

    def _join(self, obs: dict, infos: dict) -> dict:
        return {a: self._guides[a].observe(o, infos[a]) for a, o in obs.items()}


class BlackDeath(BaseParallelWrapper):
    """Keep finished agents in the outputs until every agent has finished.

    A finished agent gets a zero observation, reward 0, empty info and
    ``terminated = truncated = False`` until the last agent finishes; at that step
    every agent gets its own final flags (terminated if it was, else truncated).
    ``agents`` stays ``possible_agents`` for the whole episode, and actions for
    finished agents are dropped.
    """

    def reset(self, seed=None, options=None):
        obs, infos = self.env.reset(seed=seed, options=options)
        self.agents = list(self.env.possible_agents)
        self._final: dict[str, bool] = {}  # finished agent -> terminated (else truncated)
        return self._fill(obs), {a: infos.get(a, {}) for a in self.agents}

    def step(self, actions):
        live = {a: actions[a] for a in self.env.agents}
        obs, rewards, terms, truncs, infos = self.env.step(live)
        for a in live:
            if terms[a] or truncs[a]:
                self._final[a] = bool(terms[a])
        done = not self.env.agents
        terminated = {a: done and self._final.get(a, False) for a in self.possible_agents}
        truncated = {a: done and not self._final.get(a, False) for a in self.possible_agents}
        rewards = {a: rewards.get(a, 0.0) for a in self.possible_agents}
        infos = {a: infos.get(a, {}) for a in self.possible_agents}
        if done:
            self.agents = []
        return self._fill(obs), rewards, terminated, truncated, infos

    def _fill(self, obs: dict) -> dict:
        return {a: obs[a] if a in obs else np.zeros(self.observation_space(a).shape,
                                                     self.observation_space(a).dtype)
                for a in self.possible_agents}


def black_death(env) -> BlackDeath:
    """:class:`BlackDeath` around a ParallelEnv (for SuperSuit's vector-env conversions)."""
    return BlackDeath(env)
