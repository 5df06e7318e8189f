"""3D ground truth (labels["objects"]), the evaluation protocols built on it, and twins that differ
only by the condition. Weather is drawn (not the defaults), so a twin that kept a default instead of
the drawn value would fail."""

import json

import numpy as np
import pytest

from fusion.data import FrameDataset
from fusion.metrics import box_iou
from fusion.protocol import RANGE_BINS, Protocol, detection_ranges, frame_labels
from sensors.camera import lighting_for
from sensors.dataset import DatasetReader
from sensors.generate import GenerateConfig, generate, plan
from sensors.labels import OBJECT_FIELDS, REFERENCE_MAX_OUTSIDE
from sensors.rig import Calibration
from sim.errors import UserError
from sim.scenario import Context, stream
from sim.weather import (
    CLEAR_VISIBILITY_M,
    DAYLIGHT_LUX,
    OVERCAST_LUX,
    WeatherState,
    light_for,
    sample_weather_and_twin,
)

CONFIG = GenerateConfig(contexts=("city", "fog", "night"), frames_per_context=1, sequence_length=1, seed=21,
                        twins=True, severities=(4, 5))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("gt")
    generate(CONFIG, out, workers=1, progress=False)
    return out, DatasetReader(out), DatasetReader(out, clear=True)


def _frames_of(reader, context):
    return [i for i in range(len(reader)) if reader.meta(i)["context"] == context]


def test_objects_are_stored_with_every_frame_and_readable_with_json(data):
    root, reader, _ = data
    shard = json.loads((root / "shard-00000" / "frames.json").read_text())
    objects = shard["frames"][0]["labels"]["objects"]
    assert set(objects) == set(OBJECT_FIELDS)
    n = len(objects["ids"])
    assert n > 0 and all(len(objects[k]) == n for k in OBJECT_FIELDS)
    assert np.array(objects["center"]).shape == (n, 3) and np.array(objects["size"]).shape == (n, 3)
    assert all(r <= 100.0 + 1e-6 for r in objects["range_m"])  # the radar's 288 x 0.3472 m
    calib = Calibration.from_dict(reader.meta(0)["calibration"])
    xy = np.array(objects["center"])[:, :2] - calib.ego_from_radar[:2, 3]
    np.testing.assert_allclose(np.hypot(xy[:, 0], xy[:, 1]), objects["range_m"], atol=2e-3)
    observed = [(max(a, b) >= 6) or lp >= 1 or rc >= 1 for a, b, lp, rc in
                zip(objects["camera_left_px"], objects["camera_right_px"], objects["lidar_points"], objects["radar_cells"])]
    assert observed == objects["observed"]


def test_an_older_dataset_format_gets_an_error_naming_its_version(data, tmp_path):
    root, _, _ = data
    manifest = json.loads((root / "manifest.json").read_text())
    manifest["format_version"] = 1
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(UserError, match="format version 1 .*no 3D ground truth.*regenerate"):
        DatasetReader(tmp_path)


def test_ground_truth_does_not_change_with_the_weather(data):
    """Observability is measured on the clean render: a fog frame and its clear twin have the same
    3D ground truth, and so the same reference boxes (the degraded BEV flags do differ)."""
    _, reader, clear = data
    for i in range(len(reader)):
        assert reader.labels(i)["objects"] == clear.labels(i)["objects"]
        a = frame_labels(reader.labels(i), reader.meta(i), "reference")
        b = frame_labels(clear.labels(i), clear.meta(i), "reference")
        for frame in ("camera_left", "camera_right", "bev"):
            for key in ("ids", "labels", "boxes", "difficult", "distance_m"):
                assert a[frame][key] == b[frame][key], (frame, key)


def test_twins_keep_the_drawn_clear_air_visibility_and_light(data):
    _, reader, clear = data
    for i in _frames_of(reader, "fog"):
        w, t = reader.meta(i)["weather"], clear.meta(i)["weather"]
        assert w["fog_visibility_m"] < 300  # severity 4-5
        assert CLEAR_VISIBILITY_M[0] <= t["fog_visibility_m"] <= CLEAR_VISIBILITY_M[1]
        assert t["fog_visibility_m"] != 20_000.0  # drawn, not the default
        assert t["illuminance_lux"] == w["illuminance_lux"]  # fog is overcast in both: only the fog differs
        assert w["overcast"] is True and t["overcast"] is True  # no direct sun in the twin either
        assert OVERCAST_LUX[0] <= w["illuminance_lux"] <= OVERCAST_LUX[1]
    for i in _frames_of(reader, "night"):
        w, t = reader.meta(i)["weather"], clear.meta(i)["weather"]
        assert t["fog_visibility_m"] == w["fog_visibility_m"] != 20_000.0  # drawn clear air, kept
        assert w["overcast"] is False and t["overcast"] is False
        assert w["illuminance_lux"] < 10 and DAYLIGHT_LUX[0] <= t["illuminance_lux"] <= DAYLIGHT_LUX[1]
        a, b = reader[i], clear[i]
        # night is the light alone: the active sensors are bit-identical to the daylight twin
        for name in ("lidar_points", "lidar_bev", "fwd_lidar", "radar_polar", "radar_bev"):
            assert np.array_equal(a[name], b[name]), name
        assert a["camera_right"].mean() < 0.5 * b["camera_right"].mean()


def test_twin_weather_comes_from_the_same_draws_as_the_frame():
    for spec in plan(CONFIG):
        rng = stream(spec.seed, "weather")
        state, twin = sample_weather_and_twin(rng, Context.parse(spec.context).conditions, spec.severity)
        assert twin.rain_mm_h == twin.snow_mm_h == twin.water_film_mm == 0 and twin.lens_coverage_pct == (0, 0)
        if spec.context != "fog":
            assert twin.fog_visibility_m == state.fog_visibility_m
        if spec.context != "night":
            assert twin.illuminance_lux == state.illuminance_lux


@pytest.mark.parametrize("context", ["fog", "rain", "snow", "fog+rain"])
@pytest.mark.parametrize("severity", [1, 3, 5])
def test_twins_of_fog_rain_and_snow_are_lit_like_their_frame(context, severity):
    """The light is not what a fog, rain or snow twin studies: the camera gets the same sun and sky
    for both. (Found on the fog twins: the twin lost the frame's overcast and was rendered with direct
    sun at the 2-10 deg elevation its overcast illuminance maps to, long shadows and glare that no
    frame of either kind has.)"""
    for seed in range(4):
        rng = stream(100 * seed + severity, "weather")
        state, twin = sample_weather_and_twin(rng, Context.parse(context).conditions, severity)
        assert state.sky_overcast and twin.sky_overcast
        az = 40.0 * seed
        a = lighting_for(state, light_for(state, az), np.zeros((0, 3)), [])
        b = lighting_for(twin, light_for(twin, az), np.zeros((0, 3)), [])
        assert a.sun_normal_lux == b.sun_normal_lux == 0.0
        assert a.sky_lux == b.sky_lux == state.illuminance_lux
        assert twin.rain_mm_h == twin.snow_mm_h == 0 and twin.fog_visibility_m >= CLEAR_VISIBILITY_M[0]


def test_the_sky_follows_the_hydrometeors_unless_set():
    assert not WeatherState().sky_overcast
    assert WeatherState(fog_visibility_m=1500.0).sky_overcast
    assert not WeatherState(fog_visibility_m=2500.0).sky_overcast
    assert WeatherState(rain_mm_h=0.5).sky_overcast and WeatherState(snow_mm_h=0.1).sky_overcast
    assert WeatherState(overcast=True).sky_overcast and not WeatherState(rain_mm_h=2.0, overcast=False).sky_overcast
    with pytest.raises(UserError, match="overcast must be True, False or None"):
        WeatherState(overcast="yes")
    lit = lighting_for(WeatherState(illuminance_lux=20_000.0), light_for(WeatherState(illuminance_lux=20_000.0), 0.0),
                       np.zeros((0, 3)), [])
    assert lit.sun_normal_lux > 0  # clear sky: direct sun


def test_reference_boxes_are_the_visible_boxes_of_unoccluded_objects(data):
    """Two independent constructions agree where they must: the projected 3D box and the tight box
    of the rendered pixels of an object that nothing hides and the border does not cut."""
    _, reader, _ = data
    checked = 0
    for i in range(len(reader)):
        ref = frame_labels(reader.labels(i), reader.meta(i), "reference")["camera_right"]
        vis = reader.labels(i)["camera_right"]
        for aid, box in zip(ref["ids"], ref["boxes"]):
            if aid not in vis["ids"]:
                continue
            k = vis["ids"].index(aid)
            b = np.array(vis["boxes"][k])
            # vehicles: a person's or rider's mesh fills far less of its box than a car body does
            if vis["labels"][k] > 4 or vis["occlusion"][k] > 0 or vis["truncation"][k] > 0 or b[3] - b[1] < 12:
                continue
            assert box_iou(np.array([box]), b[None])[0, 0] > 0.75, (i, aid, box, b)
            checked += 1
    assert checked >= 3


def test_reference_protocol_rules(data):
    _, reader, _ = data
    for i in range(len(reader)):
        meta, labels = reader.meta(i), reader.labels(i)
        r_max = Protocol().r_max(meta["calibration"])
        assert r_max == pytest.approx(51.2)  # the cpu BEV grid's forward extent
        ref = frame_labels(labels, meta, "reference")
        objects = labels["objects"]
        row = {a: k for k, a in enumerate(objects["ids"])}
        for frame in ("camera_left", "camera_right"):
            lab = ref[frame]
            W, H = meta["calibration"][frame]["width"], meta["calibration"][frame]["height"]
            for aid, box, d, tr in zip(lab["ids"], lab["boxes"], lab["difficult"], lab["truncation"]):
                k = row[aid]
                assert objects["range_m"][k] <= r_max
                assert 0 <= box[0] < box[2] <= W and 0 <= box[1] < box[3] <= H
                assert d == (not objects["observed"][k] or tr > REFERENCE_MAX_OUTSIDE)
        # an object no sensor saw is never to be found; an observed one in range and in view is
        for k, aid in enumerate(objects["ids"]):
            if aid in ref["camera_right"]["ids"] and not objects["observed"][k]:
                assert ref["camera_right"]["difficult"][ref["camera_right"]["ids"].index(aid)]
        bev = ref["bev"]
        for aid, d, dist in zip(bev["ids"], bev["difficult"], bev["distance_m"]):
            if not (aid in row and objects["observed"][row[aid]] and dist <= r_max):
                assert d
    # the protocol counts objects the camera-centric one ignores
    n_ref = sum(sum(not d for d in frame_labels(reader.labels(i), reader.meta(i), "reference")["camera_right"]["difficult"])
                for i in range(len(reader)))
    n_vis = sum(sum(not d for d in reader.labels(i)["camera_right"]["difficult"]) for i in range(len(reader)))
    assert n_ref > n_vis


def test_training_targets_follow_the_protocol(data):
    root, reader, _ = data
    i = _frames_of(reader, "city")[0]
    for protocol in ("reference", "visible"):
        _, targets, _ = FrameDataset(root, [i], sensors=("camera_right",), protocol=protocol)[0]
        lab = frame_labels(reader.labels(i), reader.meta(i), protocol)["camera_right"]
        keep = [b for b, d in zip(lab["boxes"], lab["difficult"]) if not d]
        np.testing.assert_allclose(targets["camera_right"]["boxes"].numpy(), np.array(keep, np.float32).reshape(-1, 4))


def test_detection_ranges_recover_the_objects_range(data):
    """The flat-ground range of a reference box's bottom edge and the BEV box centre's range give
    back each object's range (the foot point lies on the road)."""
    _, reader, _ = data
    errs = []
    for i in range(len(reader)):
        meta = reader.meta(i)
        ref = frame_labels(reader.labels(i), meta, "reference")
        lab = ref["camera_right"]
        ok = [k for k, (t, b) in enumerate(zip(lab["truncation"], lab["boxes"])) if t == 0 and b[3] < 187]
        if ok:
            r = detection_ranges(np.array(lab["boxes"])[ok], "camera_right", meta["calibration"])
            d = np.array(lab["distance_m"])[ok]
            errs.extend(np.abs(r - d) / d)
        bev = ref["bev"]
        r = detection_ranges(np.array(bev["boxes"]), "bev", meta["calibration"])
        inside = np.array(bev["distance_m"]) < 45
        np.testing.assert_allclose(r[inside], np.array(bev["distance_m"])[inside], atol=3.0)
    # the bottom edge of a box is its nearest corner, so the camera range is a little short
    assert len(errs) > 5 and np.median(errs) < 0.15


def test_score_per_range_bin_counts_each_bin_alone(data):
    """Ground truth as detections scores 1 in every bin that holds vehicles; removing the detections
    of one bin makes that bin 0 and leaves the others at 1."""
    from fusion.late import Detections
    from study.engine.scoring import score

    _, reader, _ = data
    per_frame = []
    for i in range(len(reader)):
        meta = dict(reader.meta(i), dataset_index=i)
        lab = frame_labels(reader.labels(i), meta, "reference")["camera_right"]
        keep = [k for k, d in enumerate(lab["difficult"]) if not d]
        per_frame.append((meta, Detections(np.array(lab["boxes"], float).reshape(-1, 4)[keep], np.ones(len(keep)),
                                           np.array(lab["labels"], np.int64)[keep])))
    full = score(per_frame, reader, "camera_right", protocol="reference")
    assert full["protocol"]["name"] == "reference" and full["map_vehicles"] == 1.0
    filled = {k: v for k, v in full["map_vehicles_per_range"].items() if v is not None}
    assert filled and all(v == 1.0 for v in filled.values())
    name = next(iter(filled))
    lo, hi = (float(x) for x in name.split("-"))
    assert (lo, hi) in set(zip(RANGE_BINS[:-1], RANGE_BINS[1:]))
    cut = []
    for meta, d in per_frame:
        r = detection_ranges(d.boxes, "camera_right", meta["calibration"])
        keep = ~((r >= lo) & (r < hi))
        cut.append((meta, Detections(d.boxes[keep], d.scores[keep], d.labels[keep])))
    part = score(cut, reader, "camera_right", protocol="reference")["map_vehicles_per_range"]
    assert part[name] == 0.0
    assert all(part[k] == 1.0 for k in filled if k != name)


def test_labels_command_counts_what_each_protocol_asks_for(data, capsys):
    from study.cli import main

    root, reader, _ = data
    assert main(["labels", str(root), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for protocol in ("visible", "reference"):
        to_find = sum(c["to_find"] for c in out["protocols"][protocol]["camera_right"]["vehicles"].values())
        expect = sum(sum(1 for cls, d in zip(lab["labels"], lab["difficult"]) if cls <= 4 and not d)
                     for lab in (frame_labels(reader.labels(i), reader.meta(i), protocol)["camera_right"]
                                 for i in range(len(reader))))
        assert to_find == expect
    assert main(["labels", str(root), "--protocols", "reference,bogus"]) == 2
