"""Unit tests of the event geometry on hand-made shapes."""

import math

import numpy as np

from cosim.geometry import Polyline, Raster, convex_overlap, rect_circle_overlap, rect_corners


def test_rect_corners_rotate_about_centre():
    c = rect_corners(10.0, 5.0, math.pi / 2, 4.0, 2.0)
    # heading north: length along y, width along x
    assert np.allclose(c.min(axis=0), [9.0, 3.0])
    assert np.allclose(c.max(axis=0), [11.0, 7.0])


def test_overlapping_and_separated_cars():
    a = rect_corners(0, 0, 0, 4.5, 1.8)
    assert convex_overlap(a, rect_corners(4.0, 0, 0, 4.5, 1.8))  # rear-end, 0.5 m overlap
    assert not convex_overlap(a, rect_corners(5.0, 0, 0, 4.5, 1.8))  # 0.5 m gap behind
    # side by side with 0.5 m between them: a near miss
    assert not convex_overlap(a, rect_corners(0, 1.8 + 0.5, 0, 4.5, 1.8))
    assert convex_overlap(a, rect_corners(0, 1.7, 0, 4.5, 1.8))


def test_rotated_rectangles_need_all_axes():
    # a 45-degree car whose bounding box overlaps but whose body does not
    a = rect_corners(0, 0, 0, 4.0, 2.0)
    b = rect_corners(3.9, 2.9, math.pi / 4, 4.0, 1.0)
    assert not convex_overlap(a, b)
    assert convex_overlap(a, rect_corners(3.0, 1.5, math.pi / 4, 4.0, 1.0))


def test_rect_circle_near_miss_and_hit():
    car = rect_corners(0, 0, 0, 4.5, 1.8)
    assert rect_circle_overlap(car, 2.25 + 0.2, 0, 0.3)  # pedestrian touching the bumper
    assert not rect_circle_overlap(car, 0, 0.9 + 0.5 + 0.3, 0.3)  # 0.5 m beside the door
    assert rect_circle_overlap(car, 0, 0, 0.3)  # inside


def test_polyline_projection_and_sides():
    p = Polyline.from_points(np.array([[0, 0], [10, 0], [10, 10]]))
    assert p.length == 20
    s, lat = p.project(5, 1)
    assert s == 5 and lat == 1  # left of travel is positive
    s, lat = p.project(11, 5)
    assert s == 15 and lat == -1
    assert np.allclose(p.point_at(12), [10, 2])
    ss, lats = p.project_many(np.array([[5, 1], [11, 5]]))
    assert np.allclose(ss, [5, 15]) and np.allclose(lats, [1, -1])


def test_raster_lane_and_polygon_painting():
    r = Raster((0, 0, 20, 20), 0.25)
    r.paint_polyline(np.array([[0, 5], [20, 5]]), 1.75)
    inside = r.lookup(np.array([[10, 5], [10, 6.6], [10, 7.0], [-1, 5]]))
    assert inside.tolist() == [True, True, False, False]
    r.paint_polygon(np.array([[12, 10], [18, 10], [15, 16]]))  # a triangle
    assert r.lookup(np.array([[15, 12], [13, 15]])).tolist() == [True, False]
