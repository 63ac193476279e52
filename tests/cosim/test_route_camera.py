"""The route camera (``obs="route"``; docs/task.md, "The route variant"): each AC's own route
ahead drawn on the ground of its own camera frame in ROUTE_COLOR.

The drawn pixels are checked against the camera's own view and projection matrices (pybullet's,
not the mirror's ground rays): every route pixel's ground point lies on the band around the
centreline, and the centreline projects onto route pixels. Hand-made routes start on env_1's
straight avenue (eastbound lanes along y = 145.2 and 148.4), its road objects left out.
"""

from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np
import pytest

import cosim
from cosim import mirror as mirror_mod
from cosim.env import CosimParallelEnv
from cosim.errors import SimulatorUnavailable
from cosim.geometry import Polyline
from cosim.mirror import (
    COLORS,
    GRASS,
    ROUTE_AHEAD,
    ROUTE_COLOR,
    ROUTE_SPACING,
    ROUTE_WIDTH,
    SKY_HORIZON,
    SKY_ZENITH,
    Mirror,
    camera_eye,
)
from cosim.roadmap import road_map
from cosim.scenario import load_scenario
from cosim.sumo_bridge import Snapshot
from cosim.wrappers import OBS_VARIANTS, observation_wrappers

pybullet = pytest.importorskip("pybullet")

POSE = (-170.0, 145.2, 0.0)  # an AC centred in the rightmost eastbound lane of env_1
SIZE = 84
F = (SIZE / 2) / math.tan(math.radians(90.0) / 2)  # focal length in pixels
SMALL = dict(background=False, pedestrians=False)


def snapshot(cars=()) -> Snapshot:
    """A Snapshot with background cars at (x, y, heading) and nothing else."""
    n = len(cars)
    return Snapshot(
        time=0.0, vehicle_ids=[f"v{i}" for i in range(n)],
        vehicle_xy=np.array([c[:2] for c in cars], float).reshape(n, 2),
        vehicle_heading=np.array([c[2] for c in cars], float), vehicle_speed=np.zeros(n),
        vehicle_length=np.full(n, 4.5), vehicle_width=np.full(n, 1.8),
        vehicle_is_ac=np.zeros(n, bool), person_ids=[], person_xy=np.zeros((0, 2)),
        person_heading=np.zeros(0), person_speed=np.zeros(0),
    )


def route_mask(img: np.ndarray) -> np.ndarray:
    return np.all(img == np.array(ROUTE_COLOR, np.uint8), axis=-1)


def magenta_like(img: np.ndarray) -> np.ndarray:
    """Anything near the route colour: red and blue high, green low."""
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > 200) & (b > 200) & (g < 100)


def straight(length: float = ROUTE_AHEAD) -> np.ndarray:
    s = np.arange(0.0, length + 1e-9, ROUTE_SPACING)
    return np.stack([POSE[0] + s, np.full_like(s, POSE[1])], axis=1)


def turn(side: int, run: float = 8.0, radius: float = 15.0) -> np.ndarray:
    """``run`` metres straight ahead of POSE, then a quarter circle to the left (side = +1) or
    right (-1)."""
    lead = np.arange(0.0, run, ROUTE_SPACING)
    a = np.arange(0.0, math.pi / 2, ROUTE_SPACING / radius)
    xs = np.concatenate([POSE[0] + lead, POSE[0] + run + radius * np.sin(a)])
    ys = np.concatenate([np.full_like(lead, POSE[1]), POSE[1] + side * radius * (1 - np.cos(a))])
    return np.stack([xs, ys], axis=1)


class Camera:
    """The view and projection pybullet renders a pose's camera with, and their inverse."""

    def __init__(self, m: Mirror, pose):
        eye, forward = camera_eye(*pose, m.vehicle.length)
        view = np.array(pybullet.computeViewMatrix(eye, eye + forward, (0, 0, 1)), float).reshape(4, 4).T
        proj = np.array(m._projection, float).reshape(4, 4).T
        self.eye, self.clip = eye, proj @ view
        self.inverse = np.linalg.inv(self.clip)

    def pixel(self, xy: np.ndarray) -> np.ndarray:
        """(row, column) of ground points (k, 2) at z = 0."""
        pts = np.concatenate([xy, np.zeros((len(xy), 1)), np.ones((len(xy), 1))], axis=1)
        c = pts @ self.clip.T
        ndc = c[:, :2] / c[:, 3:]
        return np.stack([(1 - ndc[:, 1]) / 2 * SIZE, (ndc[:, 0] + 1) / 2 * SIZE], axis=1)

    def ground(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Where pixel centres' rays meet z = 0: (k, 2) world metres."""
        ndc = np.stack([(cols + 0.5) / SIZE * 2 - 1, 1 - (rows + 0.5) / SIZE * 2], axis=1)
        ends = []
        for z in (-1.0, 1.0):
            h = np.concatenate([ndc, np.full((len(ndc), 1), z), np.ones((len(ndc), 1))], axis=1) @ self.inverse.T
            ends.append(h[:, :3] / h[:, 3:])
        a, b = ends
        t = a[:, 2] / (a[:, 2] - b[:, 2])
        return (a + t[:, None] * (b - a))[:, :2]


def distance_to(path: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return np.abs(Polyline.from_points(path).project_many(pts)[1])


def check_projection(m: Mirror, img: np.ndarray, route: np.ndarray, pose=POSE) -> None:
    """The drawn pixels lie where the route's centreline projects with this camera's matrices."""
    cam = Camera(m, pose)
    rows, cols = np.nonzero(route_mask(img))
    ground = cam.ground(rows, cols)
    ahead = np.hypot(*(ground - cam.eye[:2]).T)
    near = ahead < 15.0  # where a pixel's footprint is small (far ones are widened to a pixel)
    assert near.sum() > 100
    # a pixel's footprint reaches half a column across and half a row along the view
    tolerance = ROUTE_WIDTH / 2 + ahead[near] / F + ahead[near] ** 2 / (F * mirror_mod.CAMERA_HEIGHT)
    assert (distance_to(route, ground[near]) <= tolerance).all()
    # and the centreline, from 3 to 30 m ahead of the eye, lands on route pixels
    forward = (route - cam.eye[:2]) @ np.array([math.cos(pose[2]), math.sin(pose[2])])
    on = route[(forward > 3.0) & (forward < 30.0)]
    pix = np.floor(cam.pixel(on)).astype(int)
    inside = (pix >= 0).all(axis=1) & (pix < SIZE).all(axis=1)
    assert inside.sum() > 20
    assert route_mask(img)[pix[inside, 0], pix[inside, 1]].all()


@pytest.fixture(scope="module")
def mirror():
    """env_1's avenue without its road objects (poles, walls): nothing but a car can hide a
    hand-made route, however it turns."""
    bare = dataclasses.replace(load_scenario("env_1"), additional=())
    m = Mirror(road_map(bare), max_cars=2, max_pedestrians=2)
    yield m
    m.close()


# -- where the route is drawn -----------------------------------------------------------------


def test_a_straight_route_is_a_band_in_the_lower_middle(mirror):
    mirror.sync(snapshot())
    plain, drawn = mirror.cameras([POSE, POSE], routes=[None, straight()])
    assert route_mask(plain).sum() == 0
    mask = route_mask(drawn)
    rows, cols = np.nonzero(mask)
    assert mask.sum() > 300
    horizon = SIZE / 2 + F * math.tan(mirror_mod.CAMERA_PITCH)  # 38.3: the ground starts below it
    assert rows.min() > horizon
    assert abs(cols.mean() - (SIZE / 2 - 0.5)) < 1.0 and cols.min() > 30 and cols.max() < 54
    # at the bottom row the band is ROUTE_WIDTH wide at that row's ground depth, centred
    bottom = np.flatnonzero(mask[-1])
    depth = mirror_mod.CAMERA_HEIGHT / -math.sin(mirror_mod.CAMERA_PITCH - math.atan((SIZE / 2 - 0.5) / F))
    depth *= math.cos(math.atan((SIZE / 2 - 0.5) / F))  # along the view axis
    assert abs(len(bottom) - ROUTE_WIDTH * F / depth) <= 2
    assert abs(bottom.mean() - (SIZE / 2 - 0.5)) <= 0.5
    # every row of it holds one run of pixels that narrows towards the horizon
    widths = mask.sum(axis=1)[rows.min():]
    assert (widths > 0).all() and widths[-1] > widths[0]
    # elsewhere the frame is the plain camera's
    assert np.array_equal(drawn[~mask], plain[~mask])
    check_projection(mirror, drawn, straight())


@pytest.mark.parametrize("side", [+1, -1], ids=["left", "right"])
def test_a_turning_route_bends_its_way(mirror, side):
    mirror.sync(snapshot())
    route = turn(side)
    img = mirror.cameras([POSE], routes=[route])[0]
    mask = route_mask(img)
    rows, cols = np.nonzero(mask)
    centre = SIZE / 2 - 0.5
    low = cols[rows >= 70]  # the first metres: straight ahead
    high = cols[rows <= rows.min() + 2]  # the turn, far up the image
    assert abs(low.mean() - centre) < 1.5
    if side > 0:  # a left turn bends left: its far pixels lie left of the centre
        assert high.mean() < centre - 8 and high.min() < 20
    else:
        assert high.mean() > centre + 8 and high.max() > SIZE - 20
    check_projection(mirror, img, route)


def test_nearer_objects_hide_the_route(mirror):
    mirror.sync(snapshot())
    open_road = route_mask(mirror.cameras([POSE], routes=[straight()])[0])
    mirror.sync(snapshot(cars=[(POSE[0] + 12.0, POSE[1], 0.0)]))  # a car on the route, 12 m ahead
    img = mirror.cameras([POSE], routes=[straight()])[0]
    hidden = route_mask(img)
    r, g, b = (img[..., k].astype(int) for k in range(3))
    car = (b > 130) & (r < 60) & (g < 90)  # its blue back
    assert car.sum() > 50 and not (hidden & car).any()
    assert (hidden <= open_road).all() and hidden.sum() < open_road.sum()
    assert hidden[60:].sum() == open_road[60:].sum()  # in front of the car the band is whole


def test_egl_draws_the_route_on_its_ground_meshes_and_hides_it_behind_a_car():
    """EGL draws the ground as meshes: the route is painted where the depth buffer's nearest
    surface is the ground, so it matches TinyRenderer's and a car still hides it."""
    rm = road_map(load_scenario("env_1"))
    try:
        egl = Mirror(rm, renderer="egl", max_cars=2, max_pedestrians=2)
    except SimulatorUnavailable as exc:
        pytest.skip(f"no EGL here: {exc}")
    with egl, Mirror(rm, max_cars=2, max_pedestrians=2) as tiny:
        for m in (egl, tiny):
            m.sync(snapshot(cars=[(POSE[0] + 12.0, POSE[1], 0.0)]))
        on_egl = route_mask(egl.cameras([POSE], routes=[straight()])[0])
        on_tiny = route_mask(tiny.cameras([POSE], routes=[straight()])[0])
        assert on_egl.sum() > 200
        assert (on_egl & on_tiny).sum() / (on_egl | on_tiny).sum() > 0.95
        egl.sync(snapshot())
        assert route_mask(egl.cameras([POSE], routes=[straight()])[0]).sum() > on_egl.sum()


# -- whose route ------------------------------------------------------------------------------


def test_an_ac_sees_its_own_route_and_never_another_acs():
    """env_1's ac_0 and ac_1 drive side by side eastbound (lanes 0 and 1): each one's camera
    would show the other's route too, but shows only its own."""
    env = cosim.parallel_env("env_1", obs="route", num_agents=2, seed=0, **SMALL)
    only_first = cosim.parallel_env("env_1", num_agents=2, seed=0, draw_route=["ac_0"], **SMALL)
    try:
        obs, _ = env.reset(seed=4)
        base = env.unwrapped
        m, world = base.mirror, base.world
        for me, other in (("ac_0", "ac_1"), ("ac_1", "ac_0")):
            x, y, h, _ = world.ac_state(me)
            mine = world.route(me).ahead(x, y, ROUTE_AHEAD, ROUTE_SPACING)
            own = route_mask(m.cameras([(x, y, h)], routes=[mine])[0])
            # the other's route ahead of the other AC, and the stretch of it beside this one
            ox, oy = world.ac_state(other)[:2]
            theirs = route_mask(m.cameras([(x, y, h)] * 2, routes=[
                world.route(other).ahead(ox, oy, ROUTE_AHEAD, ROUTE_SPACING),
                world.route(other).ahead(x, y, ROUTE_AHEAD, ROUTE_SPACING)])).any(axis=0)
            seen = route_mask(obs[me])
            assert seen.sum() > 100 and np.array_equal(seen, own)
            assert (theirs & ~own).sum() > 30  # the other route is in view, and not drawn
            assert not (seen & theirs & ~own).any()
            check_projection(m, obs[me], mine, pose=(x, y, h))
        obs, _ = only_first.reset(seed=4)
        assert route_mask(obs["ac_0"]).sum() > 100 and route_mask(obs["ac_1"]).sum() == 0
        assert only_first.route_agents == frozenset({"ac_0"})
    finally:
        env.close()
        only_first.close()


# -- the variants differ only by the route ----------------------------------------------------


def test_the_route_colour_is_far_from_every_other_layers():
    shades = np.linspace(0.55, 1.1, 12)  # lit surfaces come out at 0.6-1.0 of their colour
    others = [np.array(c[:3]) * 255 * k for c in COLORS.values() for k in shades]
    others += [np.array(GRASS), np.array(SKY_HORIZON), np.array(SKY_ZENITH)]
    gap = min(np.abs(np.array(ROUTE_COLOR) - np.clip(o, 0, 255)).max() for o in others)
    assert gap > 100


def test_image_frames_have_no_route_colour_and_route_frames_add_only_the_route():
    env = cosim.parallel_env("env_3", obs="route", frame_stack=2, num_agents=3, seed=0, horizon=8)
    try:
        assert env.observation_space("ac_0").shape == (84, 84, 6)
        obs, _ = env.reset(seed=1)
        base = env.unwrapped
        checked = 0
        while env.agents and checked < 4:
            poses = [base.world.ac_state(a)[:3] for a in env.agents]
            plain = base.mirror.cameras(poses)  # obs="image" at this very moment
            drawn_pixels = 0
            for a, img in zip(env.agents, plain, strict=True):
                assert magenta_like(img).sum() == 0
                drawn = obs[a][..., -3:]
                mask = route_mask(drawn)
                drawn_pixels += mask.sum()
                assert np.array_equal(drawn[~mask], img[~mask])
            assert drawn_pixels > 100
            checked += 1
            obs, *_ = env.step({a: 3 for a in env.agents})
        assert checked == 4
    finally:
        env.close()
    image = cosim.parallel_env("env_3", obs="image", num_agents=2, seed=0, horizon=3)
    try:
        obs, _ = image.reset(seed=1)
        assert all(magenta_like(o).sum() == 0 for o in obs.values())
    finally:
        image.close()


# -- the variant's plumbing -------------------------------------------------------------------


def test_route_is_an_observation_variant_of_the_image_space():
    assert "route" in OBS_VARIANTS
    single = cosim.single_env("env_1", obs="route", frame_stack=4, image_size=48, **SMALL)
    try:
        assert single.observation_space.shape == (48, 48, 12)
        obs, _ = single.reset(seed=0)
        assert route_mask(obs[..., -3:]).sum() > 20
        copy = pickle.loads(pickle.dumps(single.parallel.unwrapped))
        assert copy.route_agents == frozenset({"ac_0"})
        copy.close()
    finally:
        single.close()
    off = CosimParallelEnv("env_1", num_agents=1, camera=False, **SMALL)
    try:
        with pytest.raises(ValueError, match="cameras, which are off"):
            observation_wrappers(off, obs="route")
        with pytest.raises(ValueError, match="unknown agent"):
            CosimParallelEnv("env_1", num_agents=1, draw_route=["ac_7"], **SMALL)
    finally:
        off.close()


def test_the_route_ahead_stops_at_the_goal():
    route = road_map(load_scenario("env_1")).routes[0]
    x, y = route.path.point_at(route.spawn_s)
    pts = route.ahead(x, y, ROUTE_AHEAD, ROUTE_SPACING)
    steps = np.hypot(*np.diff(pts, axis=0).T)
    assert np.allclose(steps, ROUTE_SPACING)  # the avenue is straight
    assert ROUTE_AHEAD - 2 * ROUTE_SPACING < steps.sum() <= ROUTE_AHEAD
    assert np.hypot(*(pts[0] - (x, y))) < ROUTE_SPACING
    gx, gy = route.path.point_at(route.goal_s - 10.0)
    near_goal = route.ahead(gx, gy, ROUTE_AHEAD, ROUTE_SPACING)
    assert 10.0 - 2 * ROUTE_SPACING < np.hypot(*np.diff(near_goal, axis=0).T).sum() <= 10.0
    assert np.hypot(*(near_goal[-1] - route.goal_xy)) < ROUTE_SPACING
    assert len(route.ahead(*route.path.point_at(route.path.length), ROUTE_AHEAD, ROUTE_SPACING)) == 0
