"""World axes are defined once (sim/actors.py docstring): x east, y north, z up, yaw ccw.

highway-env draws y downward; the conversion must be a rotation (not a mirror), so right-hand
traffic in highway-env stays right-hand here.
"""

import numpy as np
import pytest

from sim.scenario import ScenarioSpec, pose_from, simulate
from sim.world import hw_to_world


def test_hw_conversion_is_a_rotation_not_a_mirror():
    # (x, y_hw, z_hw) -> (x, -y_hw, -z_hw): determinant +1
    m = np.diag([1.0, -1.0, -1.0])
    assert np.isclose(np.linalg.det(m), 1.0)
    np.testing.assert_allclose(hw_to_world([3.0, 4.0]), [3.0, -4.0])


def test_pose_is_right_handed():
    pose = pose_from(1.0, 2.0, np.pi / 2)
    x_axis, y_axis, z_axis = pose[:3, 0], pose[:3, 1], pose[:3, 2]
    np.testing.assert_allclose(np.cross(x_axis, y_axis), z_axis, atol=1e-12)
    np.testing.assert_allclose(x_axis, [0, 1, 0], atol=1e-12)  # yaw 90 deg faces north
    np.testing.assert_allclose(y_axis, [-1, 0, 0], atol=1e-12)  # its left is west


def _right_of(direction, offset):
    """True when `offset` lies to the right of `direction` (z-up, right-handed)."""
    return direction[0] * offset[1] - direction[1] * offset[0] < 0


@pytest.mark.parametrize("seed", [0, 1])
def test_junction_traffic_keeps_right(seed):
    scenes = simulate(ScenarioSpec(context="junction", seed=seed, frames=5, warmup_s=4.0))
    checked = 0
    for s in scenes:
        a = s.actors[(~s.actors.parked) & (s.actors.classes <= 6)]
        for c, v in zip(a.centers, a.velocities):
            speed = np.linalg.norm(v[:2])
            if speed < 1.0:
                continue
            d = v[:2] / speed
            x, y = c[:2]
            if abs(x) < 4 and abs(y) > 20 and abs(d[1]) > 0.95:  # north-south road
                assert _right_of(d, np.array([x, 0.0])), (c, v)
                checked += 1
            elif abs(y) < 4 and abs(x) > 20 and abs(d[0]) > 0.95:  # east-west road
                assert _right_of(d, np.array([0.0, y])), (c, v)
                checked += 1
    assert checked > 0


def test_rural_ego_drives_on_the_right_lane():
    s = simulate(ScenarioSpec(context="rural", seed=3, frames=2, warmup_s=2.0))[-1]
    ego_xy = s.ego.position[:2]
    yaw = s.ego.yaw
    fwd = np.array([np.cos(yaw), np.sin(yaw)])
    # the opposite lane's centre line is the lane polyline nearest to the ego driving the other way
    best = None
    for lane in s.road.lanes:
        d = np.linalg.norm(lane - ego_xy, axis=1)
        i = int(np.argmin(d))
        tangent = lane[min(i + 1, len(lane) - 1)] - lane[max(i - 1, 0)]
        if np.dot(tangent, fwd) < 0 and (best is None or d[i] < best[0]):
            best = (d[i], lane[i])
    assert best is not None and best[0] < 5.0
    # the oncoming lane is on the ego's left
    assert not _right_of(fwd, best[1] - ego_xy)
