"""highway-env traffic with RADIATE classes.

Every vehicle on the road, the ego included, becomes a `HydraVehicle`: highway-env's IDM/MOBIL
driver with a class, a 3D size and a gap that accounts for the real lengths of both vehicles
(highway-env's default assumes 5 m cars everywhere, so a truck behind a bus would overlap it).
"""

from __future__ import annotations

import os

os.environ["SDL_VIDEODRIVER"] = "offscreen"  # never "dummy": highway-env then renders black frames

import numpy as np  # noqa: E402
from highway_env.vehicle.behavior import IDMVehicle  # noqa: E402

from sim.actors import sample_size  # noqa: E402

# highway-env 1.12's IDM defaults (vehicle/behavior.py). Some envs overwrite IDMVehicle's class
# attributes when they are created (intersection-v2 sets COMFORT_ACC_MAX = 6, COMFORT_ACC_MIN = -3,
# DISTANCE_WANTED = 7 on the class), which would make one sequence depend on what a process
# simulated before. HydraVehicle pins them and `preserve_idm_defaults` undoes such mutations.
IDM_DEFAULTS = {
    "ACC_MAX": 6.0,  # [m/s2]
    "COMFORT_ACC_MAX": 3.0,  # [m/s2]
    "COMFORT_ACC_MIN": -5.0,  # [m/s2]
    "DISTANCE_WANTED": 10.0,  # [m] (5 m + a 5 m car; unused by HydraVehicle.desired_gap)
    "TIME_WANTED": 1.5,  # [s]
    "DELTA": 4.0,
    "POLITENESS": 0.0,
    "LANE_CHANGE_MIN_ACC_GAIN": 0.2,  # [m/s2]
    "LANE_CHANGE_MAX_BRAKING_IMPOSED": 2.0,  # [m/s2]
    "LANE_CHANGE_DELAY": 1.0,  # [s]
}


class preserve_idm_defaults:
    """Context manager: restore IDMVehicle's class attributes after building a highway-env env."""

    def __enter__(self):
        self.saved = {k: getattr(IDMVehicle, k) for k in IDM_DEFAULTS}
        return self

    def __exit__(self, *exc):
        for k, v in self.saved.items():
            setattr(IDMVehicle, k, v)
        return False


class HydraVehicle(IDMVehicle):
    """IDM vehicle with a RADIATE class and size.

    Attributes set by `adopt`: actor_id (int), cls_name (str), HEIGHT [m], LENGTH, WIDTH [m]
    (instance attributes shadow highway-env's class constants). IDM parameters are pinned to
    highway-env's defaults (IDM_DEFAULTS); layouts may set per-instance values.
    """

    actor_id: int = 0
    cls_name: str = "car"
    HEIGHT: float = 1.5
    MIN_GAP = 2.5  # bumper-to-bumper jam distance [m]
    ACC_MAX = IDM_DEFAULTS["ACC_MAX"]
    COMFORT_ACC_MAX = IDM_DEFAULTS["COMFORT_ACC_MAX"]
    COMFORT_ACC_MIN = IDM_DEFAULTS["COMFORT_ACC_MIN"]
    DISTANCE_WANTED = IDM_DEFAULTS["DISTANCE_WANTED"]
    TIME_WANTED = IDM_DEFAULTS["TIME_WANTED"]
    POLITENESS = IDM_DEFAULTS["POLITENESS"]
    LANE_CHANGE_MIN_ACC_GAIN = IDM_DEFAULTS["LANE_CHANGE_MIN_ACC_GAIN"]
    LANE_CHANGE_MAX_BRAKING_IMPOSED = IDM_DEFAULTS["LANE_CHANGE_MAX_BRAKING_IMPOSED"]
    LANE_CHANGE_DELAY = IDM_DEFAULTS["LANE_CHANGE_DELAY"]

    def desired_gap(self, ego_vehicle, front_vehicle=None, projected: bool = True) -> float:
        """IDM desired gap s* = s0 + v T + v dv / (2 sqrt(a b)), centre to centre.

        s0 = MIN_GAP + (L_ego + L_front) / 2 so the jam distance is bumper to bumper whatever
        the two lengths are (Treiber et al. 2000, with highway-env's centre-distance convention).
        """
        tau = self.TIME_WANTED
        ab = -self.COMFORT_ACC_MAX * self.COMFORT_ACC_MIN
        dv = (
            np.dot(ego_vehicle.velocity - front_vehicle.velocity, ego_vehicle.direction)
            if projected
            else ego_vehicle.speed - front_vehicle.speed
        )
        s0 = self.MIN_GAP + (ego_vehicle.LENGTH + getattr(front_vehicle, "LENGTH", 2.0)) / 2
        return s0 + ego_vehicle.speed * tau + ego_vehicle.speed * dv / (2 * np.sqrt(ab))


def adopt(
    vehicle,
    *,
    actor_id: int,
    cls_name: str,
    size: np.ndarray,
    target_speed: float | None = None,
) -> HydraVehicle:
    """Replace a highway-env vehicle by a HydraVehicle at the same state, with class and size."""
    v = HydraVehicle.create_from(vehicle)
    v.actor_id = actor_id
    v.cls_name = cls_name
    v.LENGTH, v.WIDTH, v.HEIGHT = float(size[0]), float(size[1]), float(size[2])
    v.diagonal = float(np.hypot(v.LENGTH, v.WIDTH))
    if target_speed is not None:
        v.target_speed = float(target_speed)
    if cls_name in ("bicycle",):
        v.enable_lane_change = False
    return v


def new_vehicle(
    rng: np.random.Generator, road, lane_index, longitudinal: float, speed: float, cls_name: str,
    actor_id: int,
) -> HydraVehicle:
    """A HydraVehicle placed on a lane (highway-env's make_on_lane), class-sized."""
    base = IDMVehicle.make_on_lane(road, lane_index, longitudinal=longitudinal, speed=speed)
    return adopt(base, actor_id=actor_id, cls_name=cls_name, size=sample_size(rng, cls_name))
