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


class HydraVehicle(IDMVehicle):
    """IDM vehicle with a RADIATE class and size.

    Attributes set by `adopt`: actor_id (int), cls_name (str), HEIGHT [m], LENGTH, WIDTH [m]
    (instance attributes shadow highway-env's class constants).
    """

    actor_id: int = 0
    cls_name: str = "car"
    HEIGHT: float = 1.5
    MIN_GAP = 2.5  # bumper-to-bumper jam distance [m]

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
