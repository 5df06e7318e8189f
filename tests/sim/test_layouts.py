"""sim.layouts helpers against their plain shapely formulation."""

import numpy as np
import shapely

from sim import layouts
from sim.scenario import ScenarioSpec, Simulator


def _outside_reference(rows, shapes):
    return [r for r in rows if not any(t.contains(shapely.Point(r[1], r[2])) for t in shapes)]


def test_outside_equals_point_by_point_contains():
    captured = {}
    structures = layouts.Rural.structures

    def spy(self, rng, geometry, window):
        out = structures(self, rng, geometry, window)
        captured["rows"] = out
        return out

    layouts.Rural.structures = spy
    try:
        Simulator(ScenarioSpec(context="rural", seed=4, frames=1, warmup_s=0.0))
    finally:
        layouts.Rural.structures = structures
    rows = captured["rows"]
    houses = [r for r in rows if r[0] == "building"]
    assert houses and len(rows) > 100
    rng = np.random.default_rng(0)
    # trees around the houses, some exactly on a disc's rim and at its centre
    trees = [("tree", h[1] + dx, h[2] + dy, 3.0, 3.0, 6.0, 0.0) for h in houses for dx, dy in rng.normal(0, 15, (40, 2))]
    trees += [("tree", h[1] + max(h[3], h[4]), h[2], 3.0, 3.0, 6.0, 0.0) for h in houses]
    trees += [("tree", h[1], h[2], 3.0, 3.0, 6.0, 0.0) for h in houses] + rows
    shapes = [shapely.Point(r[1], r[2]).buffer(max(r[3], r[4])) for r in houses]
    kept = layouts._outside(trees, shapes)
    assert kept == _outside_reference(trees, shapes)
    assert 0 < len(kept) < len(trees)
    assert layouts._outside([], shapes) == [] and layouts._outside(trees, []) == trees
