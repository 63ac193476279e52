"""Tests of the PyBullet mirror: geometry helpers, what the cameras see, the pool, lifecycle.

Camera tests render real pixels on a hand-built snapshot of env_1's straight avenue
(eastbound lanes along y = 145.2 and 148.4, x from -242.5 to -7.5) and check them
with colour thresholds that fail if the camera pose, the projection or the meshes
were wrong.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from cosim import meshes
from cosim import mirror as mirror_mod
from cosim.errors import SimulatorUnavailable
from cosim.meshes import prism, ribbon, triangulate
from cosim.mirror import Mirror, camera_backdrop
from cosim.roadmap import road_map
from cosim.scenario import load_scenario
from cosim.sumo_bridge import Snapshot
from cosim.viz import mosaic, side_by_side, upscale

pybullet = pytest.importorskip("pybullet")

POSE = (-170.0, 145.2, 0.0)  # an AC centred in the rightmost eastbound lane of env_1
AHEAD = 4.5 / 2 + mirror_mod.CAMERA_AHEAD  # metres from an AC's centre to its camera


def snapshot(cars=(), acs=(), pedestrians=()) -> Snapshot:
    """A Snapshot of (x, y, heading) tuples: background cars, ACs, pedestrians."""
    vehicles = list(cars) + list(acs)
    n, m = len(vehicles), len(pedestrians)
    return Snapshot(
        time=0.0,
        vehicle_ids=[f"v{i}" for i in range(n)],
        vehicle_xy=np.array([v[:2] for v in vehicles], float).reshape(n, 2),
        vehicle_heading=np.array([v[2] for v in vehicles], float),
        vehicle_speed=np.zeros(n),
        vehicle_length=np.full(n, 4.5),
        vehicle_width=np.full(n, 1.8),
        vehicle_is_ac=np.array([False] * len(cars) + [True] * len(acs), bool),
        person_ids=[f"p{i}" for i in range(m)],
        person_xy=np.array([q[:2] for q in pedestrians], float).reshape(m, 2),
        person_heading=np.array([q[2] for q in pedestrians], float),
        person_speed=np.zeros(m),
    )


def road_mask(img: np.ndarray) -> np.ndarray:
    """Pixels of the lit asphalt colour (0.27, 0.27, 0.29) -> about (68, 68, 73)."""
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r >= 50) & (r <= 90) & (abs(r - g) <= 4) & (b - r >= 2) & (b - r <= 10)


def blue_mask(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (b > 130) & (r < 60) & (g < 90)


def red_mask(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > 150) & (g < 50) & (b < 50)


def orange_mask(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > 170) & (g > 70) & (g < 150) & (b < 40)


@pytest.fixture(scope="module")
def env1_mirror():
    m = Mirror(road_map(load_scenario("env_1")))
    yield m
    m.close()


# -- pure geometry ----------------------------------------------------------------------------


def _area(verts: np.ndarray, tris: np.ndarray) -> float:
    a, b, c = verts[tris[:, 0], :2], verts[tris[:, 1], :2], verts[tris[:, 2], :2]
    return float(0.5 * np.sum((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]))


def test_triangulate_concave_polygon_covers_its_area_counter_clockwise():
    # an L shape given clockwise: area 3
    poly = np.array([[0, 0], [0, 2], [1, 2], [1, 1], [2, 1], [2, 0]], float)
    tris = triangulate(poly)
    assert len(tris) == 4
    verts = np.column_stack([poly, np.zeros(len(poly))])
    signed = [_area(verts, t[None]) for t in tris]
    assert all(s > 0 for s in signed)  # counter-clockwise: visible from above
    assert sum(signed) == pytest.approx(3.0)


def test_ribbon_has_the_lane_area_and_faces_up():
    shape = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 12.0]])  # a right-angle bend, 22 m
    verts, tris = ribbon(shape, 1.5, -1.5, 0.1)
    assert np.allclose(verts[:, 2], 0.1)
    areas = [_area(verts, t[None]) for t in tris]
    assert min(areas) > 0
    # mitred bend: area = length x width exactly
    assert sum(areas) == pytest.approx(22 * 3.0, rel=1e-6)
    seg = np.linalg.norm(np.diff(verts[: len(verts) // 2, :2], axis=0), axis=1)
    assert seg.max() <= meshes.MAX_SEGMENT + 1.5 + 1e-9  # pieces cut along the lane


def test_prism_faces_point_outwards():
    square = np.array([[0, 0], [2, 0], [2, 2], [0, 2]], float)
    verts, tris, normals = prism(square, 3.0)
    assert len(tris) == 2 + 4 * 2
    for t in tris:
        a, b, c = verts[t]
        n = np.cross(b - a, c - a)
        centre = (a + b + c) / 3 - np.array([1.0, 1.0, 1.5])
        assert np.dot(n, centre) > 0  # winding normal points away from the prism's centre
        assert np.dot(n, normals[t[0]]) > 0  # and agrees with the lighting normal


def test_backdrop_is_sky_above_the_horizon_and_grass_below():
    bd = camera_backdrop(84, 90.0)
    f = 42 / math.tan(math.radians(45))
    horizon = 42 + f * math.tan(mirror_mod.CAMERA_PITCH)  # row of elevation 0
    assert tuple(bd[int(horizon) + 2, 10]) == mirror_mod.GRASS
    assert tuple(bd[-1, 40]) == mirror_mod.GRASS
    top, near_horizon = bd[0, 0].astype(int), bd[int(horizon) - 2, 0].astype(int)
    assert top[2] > top[0] and near_horizon[2] > near_horizon[0]  # blue
    assert near_horizon.sum() > top.sum()  # lighter near the horizon


def test_mosaic_layout_and_upscale():
    ims = np.zeros((5, 4, 6, 3), np.uint8)
    ims[4] = 200
    out = mosaic(ims, cols=3, scale=2, pad=1)
    assert out.shape == (2 * (8 + 1) + 1, 3 * (12 + 1) + 1, 3)
    assert (out[10:18, 14:26] == 200).all()  # 5th image: row 1, column 1
    assert upscale(np.arange(4).reshape(2, 2), 2).tolist() == [
        [0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 3, 3], [2, 2, 3, 3]]
    assert side_by_side(np.zeros((4, 4, 3), np.uint8), np.zeros((2, 3, 3), np.uint8)).shape == (
        4, 9, 3)


# -- what the cameras see ---------------------------------------------------------------------


def test_camera_sees_the_road_and_a_car_ahead(env1_mirror):
    m = env1_mirror
    m.sync(snapshot())
    empty = m.cameras([POSE])[0]
    assert empty.shape == (84, 84, 3) and empty.dtype == np.uint8
    lower = road_mask(empty[50:, 20:64])
    assert lower.mean() > 0.7  # on a straight lane the lower centre is asphalt
    assert road_mask(empty[:30]).sum() == 0  # and the sky is not

    m.sync(snapshot(cars=[(POSE[0] + 10.0, POSE[1], 0.0)]))  # 10 m centre to centre
    with_car = m.cameras([POSE])[0]
    changed = np.abs(with_car.astype(int) - empty.astype(int)).sum(-1) > 30
    rows, cols = np.nonzero(changed)
    assert changed.sum() > 100
    # the car is straight ahead: centred, around and just below the horizon
    assert 36 <= cols.mean() <= 48 and 30 <= rows.mean() <= 55
    assert blue_mask(with_car[30:55, 30:54]).sum() > 80
    assert blue_mask(with_car[:, :20]).sum() == 0 and blue_mask(with_car[:, 64:]).sum() == 0


def test_camera_facing_away_from_the_road_sees_no_asphalt(env1_mirror):
    m = env1_mirror
    m.sync(snapshot())
    on_road = m.cameras([POSE])[0]
    assert road_mask(on_road[42:]).mean() > 0.3  # the mask does find asphalt
    # perpendicular to the avenue, from the lane (road right behind the eye): the sidewalk
    # and the wall beyond it (docs/scenarios.md); from the grass south of the wall: grass
    lane, field = m.cameras([(POSE[0], POSE[1], -math.pi / 2), (POSE[0], 130.0, -math.pi / 2)])
    assert road_mask(lane[42:]).sum() == 0 and road_mask(field[42:]).sum() == 0
    grass = np.all(field[60:] == np.array(mirror_mod.GRASS, np.uint8), axis=-1)
    assert grass.mean() > 0.5


def test_pedestrian_ahead_is_visible_in_its_colour(env1_mirror):
    m = env1_mirror
    m.sync(snapshot(pedestrians=[(POSE[0] + AHEAD + 6.0, POSE[1], 0.0)]))
    img = m.cameras([POSE])[0]
    ped = orange_mask(img)
    rows, cols = np.nonzero(ped)
    assert ped.sum() > 30
    assert 36 <= cols.mean() <= 48  # straight ahead
    assert rows.min() < 36 < rows.max()  # 1.75 m tall: crosses the eye height (horizon)


def test_own_box_is_behind_the_camera(env1_mirror):
    m = env1_mirror
    m.sync(snapshot())
    empty = m.cameras([POSE])[0]
    m.sync(snapshot(acs=[POSE]))
    own = m.cameras([POSE])[0]
    assert red_mask(own).sum() == 0
    assert np.array_equal(own, empty)
    # while another AC's camera, behind it, does see it in red
    behind = m.cameras([(POSE[0] - 10.0, POSE[1], 0.0)])[0]
    assert red_mask(behind).sum() > 80


def test_cameras_batch_matches_single_calls(env1_mirror):
    m = env1_mirror
    m.sync(snapshot(cars=[(POSE[0] + 12.0, POSE[1], 0.0)]))
    poses = [POSE, (POSE[0], POSE[1], math.pi), (-100.0, 151.6, math.pi)]
    batch = m.cameras(poses)
    assert batch.shape == (3, 84, 84, 3)
    for img, pose in zip(batch, poses, strict=True):
        assert np.array_equal(img, m.cameras([pose])[0])
    assert m.cameras([]).shape == (0, 84, 84, 3)


def test_overview_shows_road_and_grass(env1_mirror):
    img = env1_mirror.overview((160, 80))
    assert img.shape == (80, 160, 3) and img.dtype == np.uint8
    assert road_mask(img).mean() > 0.02
    assert np.all(img == np.array(mirror_mod.GRASS, np.uint8), axis=-1).mean() > 0.5
    # the avenue runs east-west through the middle of the region: a horizontal band
    rows = np.nonzero(road_mask(img).sum(axis=1) > 80)[0]
    assert len(rows) > 0 and 25 <= rows.mean() <= 55


@pytest.mark.parametrize("size, fov", [(84, 90.0), (64, 60.0)])
def test_ground_raster_matches_the_ground_meshes(env1_mirror, size, fov):
    """TinyRenderer cameras take road, sidewalks and markings from the GroundRaster; the
    same scene drawn from the meshes (as EGL and the overview draw it) must agree."""
    if (size, fov) == (84, 90.0):
        m = env1_mirror
    else:
        m = Mirror(env1_mirror.roadmap, image_size=size, fov_deg=fov, max_cars=2,
                   max_pedestrians=2)
    m.sync(snapshot(cars=[(POSE[0] + 15.0, POSE[1], 0.0)]))
    poses = [POSE, (-100.0, 151.6, math.pi), (-60.0, 148.4, 0.3), (-200.0, 146.0, -0.8)]
    raster = m.cameras(poses).astype(int)
    ground, m._ground = m._ground, None  # draw the flat layers as meshes instead
    m._show_ground_meshes(True)
    try:
        meshes = m.cameras(poses).astype(int)
    finally:
        m._ground = ground
        m._show_ground_meshes(False)
    if m is not env1_mirror:
        m.close()
    differ = np.abs(raster - meshes).sum(-1) > 60
    # what differs: raised sidewalk edges, and far markings blended (raster) vs aliased
    assert differ.mean(axis=(1, 2)).max() < 0.1
    assert road_mask(raster[:, size // 2:]).mean() > 0.3


def test_long_triangles_render_like_short_ones():
    """Guards the choice of MAX_SEGMENT: pybullet's TinyRenderer clips at the near plane.

    If a pybullet upgrade brings back bullet3 issue 1004, a 400 m quad passing under
    the camera renders differently from one cut into 2 m pieces, and this fails.
    """
    p = pybullet
    cid = p.connect(p.DIRECT)
    try:
        view = p.computeViewMatrix((3.0, 0.3, 1.4), (4.0, 0.4, 1.3), (0, 0, 1), physicsClientId=cid)
        proj = p.computeProjectionMatrixFOV(90, 1, 0.2, 100, physicsClientId=cid)
        images = []
        for cut in (400.0, 2.0):
            shape = np.array([[-200.0, 0.0], [200.0, 0.0]])
            old, meshes.MAX_SEGMENT = meshes.MAX_SEGMENT, cut
            try:
                verts, tris = ribbon(shape, 3.0, -3.0, 0.0)
            finally:
                meshes.MAX_SEGMENT = old
            vs = p.createVisualShape(p.GEOM_MESH, vertices=verts.tolist(),
                                     indices=tris.ravel().tolist(),
                                     normals=[[0, 0, 1]] * len(verts), rgbaColor=(0.3, 0.3, 0.3, 1),
                                     physicsClientId=cid)
            body = p.createMultiBody(0, -1, vs, physicsClientId=cid)
            img = p.getCameraImage(84, 84, view, proj, renderer=p.ER_TINY_RENDERER, shadow=0,
                                   physicsClientId=cid)[2]
            images.append(np.asarray(img, np.uint8).reshape(84, 84, 4)[..., :3].astype(int))
            p.removeBody(body, physicsClientId=cid)
        assert len(tris) > 100  # the short version really was cut
        grey = (images[1] < 120).all(-1)
        assert grey[:30].sum() == 0 and grey[60:].mean() > 0.3  # the reference looks right
        assert (np.abs(images[0] - images[1]).sum(-1) > 30).mean() < 0.01
    finally:
        p.disconnect(physicsClientId=cid)


# -- pool and lifecycle -----------------------------------------------------------------------


def test_pool_never_creates_bodies_and_hides_parked_ones(env1_mirror, caplog):
    m = env1_mirror
    cid = m.client
    bodies = pybullet.getNumBodies(physicsClientId=cid)
    rng = np.random.default_rng(0)
    xmin, ymin, xmax, ymax = m.roadmap.bounds
    with caplog.at_level(logging.WARNING, logger="cosim.mirror"):
        for step in range(200):
            n_cars, n_peds, n_acs = rng.integers(0, 60), rng.integers(0, 60), rng.integers(0, 7)
            pts = lambda k: [(rng.uniform(xmin, xmax), rng.uniform(ymin, ymax),  # noqa: E731
                              rng.uniform(-3, 3)) for _ in range(k)]
            m.sync(snapshot(cars=pts(n_cars), acs=pts(n_acs), pedestrians=pts(n_peds)))
            assert pybullet.getNumBodies(physicsClientId=cid) == bodies, step
    overflow = [r for r in caplog.records if "pool" in r.getMessage()]
    assert len(overflow) == 1  # 60 > 40: said once, not 200 times
    # back to an empty road: every pool body parked and invisible
    m.sync(snapshot())
    img = m.cameras([POSE])[0]
    assert blue_mask(img).sum() == 0 and orange_mask(img).sum() == 0 and red_mask(img).sum() == 0


def test_overflow_draws_the_actors_nearest_the_region_centre():
    rm = road_map(load_scenario("env_1"))
    with Mirror(rm, max_cars=1, max_pedestrians=0) as m:
        cx = (rm.bounds[0] + rm.bounds[2]) / 2  # -125
        # a camera east of the centre looking east: the far car 15 m ahead of it, the
        # near one (5 m from the centre) behind it
        eye = (cx + 30.0, POSE[1], 0.0)
        far, near = (cx + 45.0, POSE[1], 0.0), (cx - 5.0, POSE[1], 0.0)
        m.sync(snapshot(cars=[far, near], pedestrians=[(cx + 40.0, POSE[1], 0.0)]))
        assert blue_mask(m.cameras([eye])[0]).sum() == 0  # the far one is not drawn
        assert orange_mask(m.cameras([eye])[0]).sum() == 0  # nor any pedestrian (pool 0)
        assert blue_mask(m.cameras([(cx - 15.0, POSE[1], 0.0)])[0]).sum() > 80


def test_close_is_idempotent_and_disconnects():
    m = Mirror(road_map(load_scenario("env_1")), max_cars=2, max_pedestrians=2)
    cid = m.client
    assert pybullet.getConnectionInfo(physicsClientId=cid)["isConnected"] == 1
    m.close()
    m.close()
    assert m.client is None
    assert pybullet.getConnectionInfo(physicsClientId=cid)["isConnected"] == 0
    with pytest.raises(RuntimeError, match="closed"):
        m.cameras([POSE])


def test_triangle_budget_of_every_scenario(env1_mirror):
    for name in ("env_1", "env_2", "env_3", "env_4", "env_5"):
        static_meshes = meshes.build_static(road_map(load_scenario(name)))
        static = sum(mesh.triangles for mesh in static_meshes.values())
        assert 300 < static < 5000, (name, static)
        assert static_meshes["road"].triangles > 50 and static_meshes["sidewalk"].triangles > 10, name
    pool = mirror_mod.BOX_TRIANGLES * (mirror_mod.MAX_ACS + 40 + 40)
    assert env1_mirror.triangle_count == env1_mirror._static_triangles + pool


def test_bad_arguments_name_the_fix():
    rm = road_map(load_scenario("env_1"))
    with pytest.raises(ValueError, match="renderer must be one of"):
        Mirror(rm, renderer="vulkan")
    with pytest.raises(ValueError, match="image_size"):
        Mirror(rm, image_size=0)


def test_egl_unavailable_raises_and_auto_falls_back(monkeypatch, caplog):
    rm = road_map(load_scenario("env_1"))
    monkeypatch.setattr(Mirror, "_load_egl", lambda self: (False, "no EGL device", ""))
    with pytest.raises(SimulatorUnavailable, match="renderer='tiny'"):
        Mirror(rm, renderer="egl")
    with caplog.at_level(logging.INFO, logger="cosim.mirror"):
        with Mirror(rm, renderer="auto", max_cars=1, max_pedestrians=1) as m:
            assert m.renderer == "tiny"
    assert any("TinyRenderer" in r.getMessage() for r in caplog.records)


def test_egl_draws_the_meshes_like_tinyrenderer():
    """Where the EGL plugin loads (a GPU, or Mesa's llvmpipe on a CPU box) it draws the
    static meshes, read from OBJ files, in the colours TinyRenderer uses."""
    rm = road_map(load_scenario("env_1"))
    try:
        m = Mirror(rm, renderer="egl", max_cars=2, max_pedestrians=2)
    except SimulatorUnavailable as exc:
        pytest.skip(f"no EGL here: {exc}")
    with m:
        m.sync(snapshot(cars=[(POSE[0] + 10.0, POSE[1], 0.0)]))
        img = m.cameras([POSE])[0]
        assert img.shape == (84, 84, 3)
        assert road_mask(img[50:, 20:64]).mean() > 0.7
        assert blue_mask(img[30:55, 30:54]).sum() > 80
        assert road_mask(img[:30]).sum() == 0


def test_auto_never_picks_software_egl(monkeypatch):
    rm = road_map(load_scenario("env_1"))
    monkeypatch.setattr(Mirror, "_load_egl", lambda self: (True, "", "llvmpipe (LLVM 15)"))
    monkeypatch.setattr(pybullet, "unloadPlugin", lambda *a, **k: None)
    with Mirror(rm, renderer="auto", max_cars=1, max_pedestrians=1) as m:
        assert m.renderer == "tiny"


def test_missing_pybullet_is_reported_at_construction(monkeypatch):
    import sys

    rm = road_map(load_scenario("env_1"))
    monkeypatch.setitem(sys.modules, "pybullet", None)  # import pybullet -> ImportError
    with pytest.raises(SimulatorUnavailable, match="pip install"):
        Mirror(rm)
