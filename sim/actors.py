"""Actor classes (RADIATE's eight), their 3D sizes, and the columnar `Actors` record.

World frame (defined once, used everywhere): right-handed, x east, y north, z up, metres.
Yaw is counter-clockwise from +x about +z, radians. highway-env's plane has y pointing down
(its renderer draws y downward), so a highway-env point (x, y) is (x, -y, 0) here and a heading
h is yaw -h: that is a 180 deg rotation about x, not a mirror, so right-hand traffic stays
right-hand (tested in tests/sim/test_axes.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# RADIATE classes, in its order; ids start at 1 (0 is background, as torchvision expects).
CLASSES: tuple[str, ...] = (
    "car",
    "van",
    "truck",
    "bus",
    "motorbike",
    "bicycle",
    "pedestrian",
    "group_of_pedestrians",
)
CLASS_ID: dict[str, int] = {name: i + 1 for i, name in enumerate(CLASSES)}
VEHICLE_CLASSES = ("car", "van", "truck", "bus", "motorbike", "bicycle")
PEDESTRIAN_CLASSES = ("pedestrian", "group_of_pedestrians")

# Mean (length, width, height) [m] and relative spread (std / mean) per class.
# car: EU C-segment hatchback; van: Transit/Sprinter; truck: rigid to articulated (7.5-16.5 m);
# bus: single-deck city bus; two-wheelers and pedestrians include the rider / a standing adult.
CLASS_SIZE: dict[str, tuple[tuple[float, float, float], float]] = {
    "car": ((4.5, 1.8, 1.5), 0.07),
    "van": ((5.4, 2.0, 2.3), 0.06),
    "truck": ((11.0, 2.5, 3.6), 0.15),
    "bus": ((12.0, 2.55, 3.1), 0.05),
    "motorbike": ((2.1, 0.8, 1.45), 0.05),
    "bicycle": ((1.75, 0.6, 1.75), 0.04),
    "pedestrian": ((0.5, 0.6, 1.72), 0.05),
    "group_of_pedestrians": ((2.2, 1.6, 1.72), 0.2),
}
# Average class heights [m] used by the BEV -> FWD mapping (HydraFusion Appendix A).
CLASS_HEIGHT: dict[str, float] = {name: size[2] for name, (size, _) in CLASS_SIZE.items()}
EGO_SIZE = (4.9, 2.0, 1.9)  # a Land Rover Discovery-sized research vehicle, like RADIATE's


def sample_size(rng: np.random.Generator, cls: str) -> np.ndarray:
    """Draw a (length, width, height) [m] for one actor of class `cls` (clipped at +-2 sigma)."""
    mean, rel = CLASS_SIZE[cls]
    mean = np.asarray(mean)
    z = np.clip(rng.normal(size=3), -2, 2)
    if cls == "group_of_pedestrians":
        z[2] *= 0.2  # the group's extent varies, people's height much less
    return mean * (1.0 + rel * z)


@dataclass(frozen=True)
class Actors:
    """Columnar record of the dynamic (and parked) actors of one frame, N rows.

    Fields:
        ids: (N,) int64, stable across frames of a sequence (> 0; the ego is not an actor).
        classes: (N,) int64, RADIATE class ids (`CLASS_ID`).
        centers: (N, 3) float64, box centre in the world frame [m] (z = height / 2 on flat ground).
        sizes: (N, 3) float64, (length, width, height) [m].
        yaws: (N,) float64, heading counter-clockwise from +x [rad].
        velocities: (N, 3) float64, world-frame velocity [m/s].
        parked: (N,) bool, parked at the kerb (never moves).
        members: (N,) int64, people in a group of pedestrians (1 for everyone else).
    """

    ids: np.ndarray
    classes: np.ndarray
    centers: np.ndarray
    sizes: np.ndarray
    yaws: np.ndarray
    velocities: np.ndarray
    parked: np.ndarray
    members: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, index) -> Actors:
        """Row selection by mask, index array or slice; returns an Actors."""
        return Actors(
            **{name: getattr(self, name)[index] for name in self.__dataclass_fields__}
        )

    @staticmethod
    def empty() -> Actors:
        return Actors(
            ids=np.zeros(0, np.int64),
            classes=np.zeros(0, np.int64),
            centers=np.zeros((0, 3)),
            sizes=np.zeros((0, 3)),
            yaws=np.zeros(0),
            velocities=np.zeros((0, 3)),
            parked=np.zeros(0, bool),
            members=np.zeros(0, np.int64),
        )

    @staticmethod
    def concat(parts: list[Actors]) -> Actors:
        parts = [p for p in parts if len(p)]
        if not parts:
            return Actors.empty()
        return Actors(
            **{
                name: np.concatenate([getattr(p, name) for p in parts])
                for name in Actors.__dataclass_fields__
            }
        )

    def class_names(self) -> list[str]:
        return [CLASSES[c - 1] for c in self.classes]

    def footprints(self) -> np.ndarray:
        """(N, 4, 2) box corners in the ground plane, counter-clockwise from rear-right [m]."""
        return box_corners_2d(self.centers[:, :2], self.sizes[:, :2], self.yaws)


def box_corners_2d(centers: np.ndarray, lw: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """Corners (N, 4, 2) of oriented rectangles: centres (N,2), (length, width) (N,2), yaw (N,)."""
    half = lw / 2.0
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)  # rear-right, ccw
    c, s = np.cos(yaws), np.sin(yaws)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (N, 2, 2)
    pts = local[None] * half[:, None, :]
    return np.einsum("nij,nkj->nki", rot, pts) + centers[:, None, :]


def boxes_overlap_2d(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test for two convex quads (4, 2)."""
    for poly in (a, b):
        for i in range(4):
            edge = poly[(i + 1) % 4] - poly[i]
            axis = np.array([-edge[1], edge[0]])
            pa, pb = a @ axis, b @ axis
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True
