"""The static world's lane paint: the batched meshing equals meshing dash by dash with shapely."""

import numpy as np
import pytest
import shapely
import shapely.ops

from sensors import world_mesh as wm
from sim.scenario import ScenarioSpec, Simulator


def reference_stripes(lines, dashed, z):
    """The paint as first written: shapely.ops.substring per dash, buffered and meshed one by one."""
    parts = []
    for line, d in zip(lines, dashed):
        ls = shapely.LineString(line)
        if ls.length < 0.5:
            continue
        if d:
            segs, s = [], 0.0
            while s < ls.length:
                segs.append(shapely.ops.substring(ls, s, min(s + wm.DASH, ls.length)))
                s += wm.DASH + wm.GAP
        else:
            segs = [ls]
        for seg in segs:
            parts.append(wm._flat(seg.buffer(wm.PAINT_WIDTH / 2, cap_style="flat"), z, "lane_paint"))
    return wm.MeshSoup.concat(parts)


def reference_zebra(rect, z):
    a, b, c, d = rect
    along = b - a
    n = int(np.linalg.norm(along) / 1.0)
    parts = []
    for k in range(n):
        t0, t1 = k / n, (k + 0.5) / n
        q = np.array([a + along * t0, a + along * t1, d + along * t1, d + along * t0])
        parts.append(wm._flat(shapely.Polygon(q), z, "lane_paint"))
    return wm.MeshSoup.concat(parts)


def assert_same_soup(a, b):
    for name in ("vertices", "faces", "material", "instance"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), name


@pytest.mark.parametrize("context", ["city", "junction", "motorway", "rural"])
def test_stripes_of_real_roads_equal_the_dash_by_dash_mesh(context):
    scene = next(Simulator(ScenarioSpec(context=context, seed=7, frames=1)).scenes())
    window = shapely.box(*scene.road.region)
    lines, dashed = wm._clip_lines(scene.road.markings, scene.road.marking_dashed, window)
    assert dashed.any() and len(lines) > 2
    assert_same_soup(wm._stripes(lines, dashed, wm.PAINT_LIFT), reference_stripes(lines, dashed, wm.PAINT_LIFT))
    for cw in scene.road.crosswalks:
        assert_same_soup(wm._zebra(np.asarray(cw), wm.PAINT_LIFT), reference_zebra(np.asarray(cw), wm.PAINT_LIFT))


def test_stripes_on_awkward_lines_equal_the_dash_by_dash_mesh():
    rng = np.random.default_rng(3)
    t = np.linspace(0, 1.3, 40)
    arc = np.column_stack([30 * np.cos(t), 30 * np.sin(t)])  # curved, many vertices
    lines = [
        arc,
        np.array([[0.0, 0.0], [9.0, 0.0], [18.0, 0.0], [27.0, 0.0]]),  # dash starts on vertices, length 3 x 9
        np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 0.0], [12.0, 0.0]]),  # a repeated vertex, dash ends on one
        np.array([[0.0, 0.0], [0.3, 0.0]]),  # shorter than 0.5 m: no paint
        np.array([[0.0, 0.0], [2.0, 0.0]]),  # shorter than one dash
        np.cumsum(rng.normal(size=(60, 2)), axis=0) * 2.0,  # a random walk
        np.array([[5.0, 5.0], [-40.0, 5.0]]),  # long, solid: cut into 20 m tiles
    ]
    for dashed in ([True] * 7, [False] * 7, [True, False, True, True, False, True, False]):
        d = np.array(dashed)
        assert_same_soup(wm._stripes(lines, d, 0.015), reference_stripes(lines, d, 0.015))
    empty = wm._stripes([np.array([[0.0, 0.0], [0.1, 0.0]])], np.array([True]), 0.015)
    assert len(empty.faces) == 0 and empty.vertices.shape == (0, 3)


def test_dashes_follow_the_pattern():
    ls = shapely.LineString([(0.0, 0.0), (20.0, 0.0)])
    dashes = wm._dashes(ls)
    starts = [d.coords[0][0] for d in dashes]
    ends = [d.coords[-1][0] for d in dashes]
    assert starts == [0.0, 9.0, 18.0] and ends == [3.0, 12.0, 20.0]
