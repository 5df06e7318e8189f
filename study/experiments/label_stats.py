"""`hydrabench labels DIR`: what each evaluation protocol asks a detector to find.

Counts, per protocol, the vehicle (car, van, truck, bus) and other ground-truth boxes in the right
camera (and the BEV), those to find and those ignored (difficult), per range bin of the objects'
range from the radar and per context; and, from the 3D ground truth, which sensors observe the
objects in the clean render (camera, lidar, radar: alone and together). This is the measurement
behind "a metric that only credits what the camera sees cannot credit radar or lidar".
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from sim.errors import UserError

VEHICLE_IDS = (1, 2, 3, 4)  # car, van, truck, bus


def label_statistics(data, protocols=("visible", "reference"), progress: bool = True) -> dict:
    """{"frames", "protocols": {name: {frame: {"vehicles": {bin: {"to_find", "ignored"}}, ...}}},
    "observed_by": {...}} for the dataset at `data` (see the module docstring)."""
    from fusion.protocol import RANGE_BINS, Protocol, frame_labels, range_bin_names
    from sensors.dataset import DatasetReader
    from sim.progress import progress as progress_bar

    reader = DatasetReader(data)
    if "objects" not in reader.labels(0):
        raise UserError(f"{data} has no 3D ground truth")
    names = range_bin_names() + [">=100"]
    edges = np.array(list(RANGE_BINS) + [np.inf])
    counts = {p: {f: {g: {b: [0, 0] for b in names} for g in ("vehicles", "other")} for f in ("camera_right", "bev")}
              for p in protocols}
    per_context = {p: defaultdict(lambda: [0, 0]) for p in protocols}
    sensors = defaultdict(int)
    n_objects = 0
    for i in progress_bar(iterable=range(len(reader)), desc="labels", unit="frame", enabled=progress):
        meta, labels = reader.meta(i), reader.labels(i)
        for p in protocols:
            gt = frame_labels(labels, meta, Protocol(p))
            for f in ("camera_right", "bev"):
                lab = gt[f]
                for cls, d, dist in zip(lab["labels"], lab["difficult"], lab["distance_m"]):
                    b = names[int(np.clip(np.searchsorted(edges, dist, side="right") - 1, 0, len(names) - 1))]
                    group = "vehicles" if cls in VEHICLE_IDS else "other"
                    counts[p][f][group][b][1 if d else 0] += 1
                    if f == "camera_right" and group == "vehicles" and not d:
                        per_context[p][meta["context"]][0] += 1
                    elif f == "camera_right" and group == "vehicles":
                        per_context[p][meta["context"]][1] += 1
        obj = labels["objects"]
        r_max = Protocol().r_max(meta["calibration"])
        for k, cls in enumerate(obj["labels"]):
            if cls not in VEHICLE_IDS or obj["range_m"][k] > r_max:
                continue
            n_objects += 1
            seen = [s for s, ok in (("camera", max(obj["camera_left_px"][k], obj["camera_right_px"][k]) >= 6),
                                    ("lidar", obj["lidar_points"][k] >= 1), ("radar", obj["radar_cells"][k] >= 1)) if ok]
            sensors["+".join(seen) or "none"] += 1

    def pack(c):
        return {"to_find": c[0], "ignored": c[1]}

    return {
        "data": str(data), "frames": len(reader),
        "protocols": {p: {f: {g: {b: pack(c) for b, c in by_bin.items()} for g, by_bin in groups.items()}
                          for f, groups in counts[p].items()} for p in protocols},
        "vehicles_per_context": {p: {c: pack(v) for c, v in sorted(per_context[p].items())} for p in protocols},
        "vehicles_within_r_max_observed_by": {"objects": n_objects, **dict(sorted(sensors.items()))},
        "r_max_m": "the BEV grid's forward extent (fusion.protocol)",
    }
