"""study.experiments.crossover: the sets dropped per sensor, the curves assembled from per-frame scores
with a known crossing on the physical axis (fog visibility falling, snow rate rising), the twins
scored on the same draws, the figures written, and the physical gate's candidates taken from the
all-branches curves only."""

import numpy as np
import pytest

from study.experiments.crossover import curves_record, drop_sets, half_widths, plot_crossovers, summary_rows
from study.experiments.physical_gate import candidates_of

BRANCHES = ("radar", "camera_right", "lidar", "radar_lidar")
SENSORS = {"radar": ("radar",), "camera_right": ("camera_right",), "lidar": ("lidar",), "radar_lidar": ("radar", "lidar")}


class RowMean:
    """A stand-in for fusion.metrics.ImageMatches: mAP over rows = the mean of per-row values."""

    def __init__(self, values):
        self.values = np.asarray(values, dtype=float)

    def mean_ap(self, rows):
        return float(np.mean(self.values[list(rows)]))


def test_dropping_a_sensor_from_late_and_from_all_branches():
    sets = drop_sets(BRANCHES, SENSORS, ["radar", "camera_right", "lidar"])
    assert sets["late"] == {"with": ("radar", "camera_right", "lidar"), "camera_right": ("radar", "lidar"),
                            "lidar": ("radar", "camera_right"), "radar": ("camera_right", "lidar")}
    assert sets["all_branches"]["lidar"] == ("radar", "camera_right")  # radar_lidar reads the lidar too
    assert sets["all_branches"]["camera_right"] == ("radar", "lidar", "radar_lidar")
    assert drop_sets(("radar",), {"radar": ("radar",)}, ["radar"])["late"] == {"with": ("radar",)}  # nothing left


def _sweep(condition, quantity, values, seqs=6, per=2):
    """Frames of one condition at len(values) levels, `seqs` sequences of `per` frames each."""
    metas = []
    for level, x in enumerate(values, start=1):
        for s in range(seqs):
            for _ in range(per):
                metas.append({"context": condition, "severity": level, "sequence_id": f"{condition}-{level}-{s}",
                              "weather": {quantity: x * (1 + 0.01 * s)}})
    return metas


def test_curves_find_the_crossing_on_the_physical_axis_with_twins_on_the_same_draws(tmp_path):
    vis = [800.0, 400.0, 200.0, 100.0, 50.0]
    snow = [0.2, 0.45, 0.8, 1.3, 2.1]
    metas = _sweep("fog", "visibility_m", vis) + _sweep("snow", "snow_mm_h", snow)
    sets = drop_sets(BRANCHES, SENSORS, ["radar", "camera_right", "lidar"])
    names = sorted({"+".join(b) for d in sets.values() for b in d.values()})  # a set's order moves with PYTHONHASHSEED, and with it the noise each name draws
    rng = np.random.default_rng(0)
    # the camera's worth: +0.04 at 800 m falling by 0.02 per halving of the visibility -> 0 at 200 m
    cam_fog = {v: 0.04 - 0.02 * np.log2(800.0 / v) for v in vis}
    # the lidar's worth in snow: +0.03 - 0.03 * rate -> 0 at 1.0 mm/h
    lid_snow = {x: 0.03 - 0.03 * x for x in snow}
    values = {n: np.full(len(metas), 0.5) + rng.normal(0, 0.002, len(metas)) for n in names}
    twin = {n: np.full(len(metas), 0.6) for n in names}
    for r, m in enumerate(metas):
        x = list(m["weather"].values())[0] / (1 + 0.01 * int(m["sequence_id"].rsplit("-", 1)[1]))
        for n in names:
            members = set(n.split("+"))
            if m["context"] == "fog" and "camera_right" in members:
                values[n][r] += cam_fog[round(x, 6)]
                twin[n][r] += 0.05
            if m["context"] == "snow" and {"lidar", "radar_lidar"} & members:
                values[n][r] += lid_snow[round(x, 6)]
            if m["context"] == "snow" and {"radar", "radar_lidar"} & members:
                values[n][r] += 0.05  # the radar pays in every snow
    rec = curves_record(metas, {n: RowMean(v) for n, v in values.items()}, {n: RowMean(v) for n, v in twin.items()},
                        sets, resamples=200, seed=0)
    fog = rec["fog"]["curves"]["late"]["camera_right"]
    assert [s["severity"] for s in rec["fog"]["steps"]] == [1, 2, 3, 4, 5]
    assert fog["steps"][0] > fog["steps"][-1]  # visibility: mild (far) to strong (near)
    assert fog["crossing_kind"] == "crossed" and fog["crossing"] == pytest.approx(200.0, rel=0.1)
    assert fog["first_resolved_below"] == pytest.approx(100.0, rel=0.06)
    assert fog["twin_estimate"] == pytest.approx([0.05] * 5, abs=1e-9) and fog["clear"]["estimate"] == pytest.approx(0.05)
    lo, hi = fog["crossing_interval"]
    assert lo is not None and hi is not None and hi <= 200.0 <= lo  # the milder end is the larger visibility
    snow_lidar = rec["snow"]["curves"]["all_branches"]["lidar"]
    assert snow_lidar["crossing"] == pytest.approx(1.0, rel=0.1) and snow_lidar["without"] == ["radar", "camera_right"]
    assert rec["snow"]["curves"]["late"]["radar"]["crossing_kind"] == "none"  # radar's worth never changes sign
    assert half_widths(rec)["median"] < 0.01
    rows = summary_rows({"conditions": rec})
    assert {(r["condition"], r["sensor"]) for r in rows if r["kind"] == "crossed"} >= {("fog", "camera_right"),
                                                                                     ("snow", "lidar")}
    cands = candidates_of({"conditions": rec})  # only the all-branches curves that go below 0
    assert set(cands) >= {("camera_right", "fog"), ("lidar", "snow")} and ("radar", "snow") not in cands
    record = {"conditions": rec, "frames_per_step": 12, "resamples": 200, "fusion": "soft-nms"}
    paths = plot_crossovers(record, tmp_path, "test CPU")
    assert [p.name for p in paths] == ["crossover.png", "crossover_fog.png", "crossover_snow.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)
