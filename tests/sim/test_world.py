"""sim.world: geometry helpers that must reproduce shapely bit for bit."""

import numpy as np
import pytest
import shapely
from shapely.geometry import GeometryCollection, LineString, MultiPolygon, Point, Polygon, box

from sim.layouts import LAYOUTS
from sim.scenario import LAYOUT_NAMES, stream
from sim.world import Polyline, distance_to_area, extract_road, outward_normals, resample, ring_lines


def _reference(area, xy):
    return shapely.distance(area, shapely.points(xy))


def _probes(area, rng, n):
    """Points inside, outside, far away, on boundary vertices and on boundary segments."""
    lo, hi = np.array(area.bounds[:2]), np.array(area.bounds[2:])
    ring = np.concatenate([shapely.get_coordinates(r) for r in shapely.get_rings(shapely.get_parts(area))])
    k = rng.integers(len(ring) - 1, size=n // 4)
    on_segments = ring[k] + rng.uniform(0, 1, (len(k), 1)) * (ring[k + 1] - ring[k])
    near = ring[rng.integers(len(ring), size=n // 4)] + rng.normal(0, 3, (n // 4, 2))
    return np.vstack([
        rng.uniform(lo - 20, hi + 20, (n, 2)),
        rng.uniform(lo - 2000, hi + 2000, (n // 8, 2)),
        ring[:: max(1, len(ring) // 50)],
        on_segments,
        near,
    ])


@pytest.mark.parametrize("name", LAYOUT_NAMES)
def test_distance_to_area_equals_shapely_on_every_layouts_road(name):
    layout = LAYOUTS.get(name)()
    road, ego = layout.make_road(stream(5, "traffic"))
    x, y = ego.position[0], -ego.position[1]
    region = (x - 250, y - 250, x + 250, y + 250)
    geometry = extract_road(road.network, region, parking_width=layout.parking_width,
                            sidewalk_offset=layout.sidewalk_offset, sidewalk_width=layout.sidewalk_width)
    rng = np.random.default_rng(0)
    for area in (geometry.road, geometry.sidewalks, geometry.road.buffer(4.0)):
        if area.is_empty:
            continue
        xy = _probes(area, rng, 1500)
        got = distance_to_area(area, xy)
        assert got.dtype == np.float64 and got.shape == (len(xy),)
        np.testing.assert_array_equal(got, _reference(area, xy))
        assert (got == 0).any() and (got > 0).any()


def test_distance_to_area_with_holes_multipolygons_and_degenerate_input():
    rng = np.random.default_rng(1)
    ring = box(0, 0, 100, 60).difference(Point(50, 30).buffer(15)).difference(box(10, 10, 20, 20))
    multi = MultiPolygon([ring, box(200, 0, 260, 40), Point(400, 400).buffer(30, quad_segs=64)])
    spiky = Polygon([(0, 0), (1000, 1), (1000, 2), (0, 3), (0, 3), (-5, 1)])  # a repeated vertex
    for area in (ring, multi, spiky):
        xy = _probes(area, rng, 2000)
        np.testing.assert_array_equal(distance_to_area(area, xy), _reference(area, xy))
    one = np.array([[50.0, 30.0]])  # the centre of a hole
    np.testing.assert_array_equal(distance_to_area(ring, one), _reference(ring, one))
    assert distance_to_area(ring, np.zeros((0, 2))).shape == (0,)
    assert np.isnan(distance_to_area(Polygon(), one)).all()
    other = GeometryCollection([LineString([(0, 0), (10, 0)]), box(20, 20, 30, 30)])
    xy = _probes(box(0, 0, 30, 30), rng, 200)
    np.testing.assert_array_equal(distance_to_area(other, xy), _reference(other, xy))


def test_outward_normals_point_away_from_the_area():
    area = box(0, 0, 100, 40)
    for line in ring_lines(area, 5.0, box(-50, -50, 150, 90)):
        n = outward_normals(line, area)
        assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
        far = _reference(area, line + 3 * n)
        assert (far > _reference(area, line)).all()


def _interpolate_reference(line, distances):
    return shapely.get_coordinates(shapely.line_interpolate_point(LineString(line), distances))


def test_polyline_points_equal_shapely_line_interpolate_point():
    rng = np.random.default_rng(2)
    for k in range(200):
        m = int(rng.integers(2, 40))
        line = np.cumsum(rng.normal(0, rng.choice([0.01, 1.0, 100.0]), (m, 2)), axis=0) + rng.uniform(-5e3, 5e3, 2)
        if k % 4 == 0:
            line[rng.integers(m)] = line[int(rng.integers(m))]  # repeated vertices, zero-length segments
        if k % 7 == 0:
            line = np.repeat(line, 2, axis=0)
        length = LineString(line).length
        seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
        polyline = Polyline(line)
        for distances in (
            np.linspace(0, length, int(rng.integers(2, 400))),
            rng.uniform(-1.2 * length, 1.2 * length, 60),  # negative: from the end
            np.cumsum(seg),  # exactly at the vertices (as GEOS adds the lengths up)
            np.array([0.0, length, 2 * length, -length, -2 * length, 1e-300, -0.0]),
            np.zeros(0),
        ):
            want = _interpolate_reference(line, distances)
            got = polyline.points(distances)
            assert got.shape == (len(distances), 2)
            np.testing.assert_array_equal(got, want)
            for d, w in zip(distances[:80], want):
                np.testing.assert_array_equal(polyline.point(float(d)), w)


def test_resample_keeps_both_ends_and_the_spacing():
    line = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 7.5]])
    pts = resample(line, 1.0)
    assert len(pts) == 18 and (pts[0] == line[0]).all() and (pts[-1] == line[-1]).all()
    np.testing.assert_allclose([LineString(line).project(Point(p)) for p in pts], np.linspace(0, 17.5, 18))
    np.testing.assert_array_equal(resample(line[:2], 100.0), line[:2])
