"""hydrabench export nuscenes: the nuScenes devkit loads the export, renders it, finds hydrabench's boxes
where its labels are, reads the splits, and its own DetectionEval scores the export's labels as AP 1
(and a copy with boxes dropped or moved as low as that implies)."""

import hashlib
import json
import math
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from nuscenes import NuScenes  # locked in requirements.lock: a broken install fails, it is not skipped
from nuscenes.eval.common.config import config_factory
from nuscenes.eval.detection.evaluate import DetectionEval
from nuscenes.utils.data_classes import LidarPointCloud, RadarPointCloud
from nuscenes.utils.geometry_utils import BoxVisibility, view_points
from nuscenes.utils.splits import get_scenes_of_split

from sensors.dataset import DatasetReader
from sensors.export import nuscenes as ns
from sensors.generate import GenerateConfig
from sensors.labels import reference_labels
from sensors.rig import Calibration
from study.experiments.nuscenes_export import SPLIT_NAMES, export_nuscenes, hydrabench_splits

matplotlib.use("Agg")

# the config other test files use (tests/study/test_train.py, tests/sensors/test_combine.py): no new dataset
CONFIG = GenerateConfig(contexts=("junction", "fog"), frames_per_context=4, sequence_length=2, seed=9)


@pytest.fixture(scope="module")
def export(shared_dataset, tmp_path_factory):
    data = shared_dataset(CONFIG)
    out = tmp_path_factory.mktemp("ns") / "export"
    summary = export_nuscenes(data, out, progress=False)
    nusc = NuScenes(version=ns.VERSION, dataroot=str(out), verbose=False)
    return data, out, summary, nusc


def _files(root: Path) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*"))
            if p.is_file()}


def test_the_devkit_loads_it_with_the_manifests_counts(export):
    data, out, summary, nusc = export
    reader = DatasetReader(data)
    frames = reader.manifest["frames"]
    labels = sum(len(reader.labels(i)["objects"]["ids"]) for i in range(len(reader)))
    assert len(nusc.sample) == len(frames) == summary["frames"]
    assert len(nusc.sample_annotation) == labels == summary["labels"]
    assert len(nusc.scene) == len(reader.manifest["shards"])
    assert len(nusc.sample_data) == 4 * len(frames)
    for sample in nusc.sample:
        assert set(sample["data"]) == {"CAM_FRONT", "CAM_FRONT_STEREO_LEFT", "LIDAR_TOP", "RADAR_TOP"}
        h = sample["hydrabench"]
        assert h["context"] == frames[h["frame"]]["context"] and h["severity"] == frames[h["frame"]]["severity"]
    for scene in nusc.scene:  # every scene names its context, condition, severity and weather
        h = scene["hydrabench"]
        assert h["context"] in scene["description"] and f"severity {h['severity']}" in scene["description"]
        assert set(h["weather"]) >= {"visibility_m", "rain_mm_h", "snow_mm_h", "illuminance_lux"}
    # the sensor files hold what the dataset holds
    first = nusc.sample[0]
    lidar = LidarPointCloud.from_file(nusc.get_sample_data_path(first["data"]["LIDAR_TOP"]))
    np.testing.assert_allclose(lidar.points[:3].T, reader[0]["lidar_points"][:, :3], atol=1e-6)
    radar = RadarPointCloud.from_file(nusc.get_sample_data_path(first["data"]["RADAR_TOP"]))
    cal = reader.meta(0)["calibration"]
    mine = ns.radar_points(reader[0]["radar_polar"], cal["radar_range_resolution_m"])
    assert radar.points.shape == (18, len(mine)) and len(mine) > 10
    np.testing.assert_allclose(radar.points[5], mine["rcs"], rtol=1e-6)


def test_the_export_is_byte_reproducible_and_instances_keep_their_token(export, tmp_path):
    data, out, _, nusc = export
    again = export_nuscenes(data, tmp_path / "again", progress=False)
    assert _files(tmp_path / "again") == _files(out) and again["bytes"] > 0
    for inst in nusc.instance:  # one instance per actor and sequence, its annotations chained in time
        token, chain = inst["first_annotation_token"], []
        while token:
            ann = nusc.get("sample_annotation", token)
            assert ann["instance_token"] == inst["token"]
            assert ann["hydrabench"]["actor_id"] == inst["hydrabench"]["actor_id"]
            chain.append(nusc.get("sample", ann["sample_token"]))
            token = ann["next"]
        assert len(chain) == inst["nbr_annotations"] and chain[-1]["token"] == nusc.get(
            "sample_annotation", inst["last_annotation_token"])["sample_token"]
        assert len({s["scene_token"] for s in chain}) == 1
        assert [s["timestamp"] for s in chain] == sorted(s["timestamp"] for s in chain)
    assert any(i["nbr_annotations"] > 1 for i in nusc.instance)


def test_a_sample_renders_to_files(export, tmp_path):
    _, _, _, nusc = export
    sample = nusc.sample[1]
    for channel in ("CAM_FRONT", "LIDAR_TOP", "RADAR_TOP"):
        # the map underlay is off: with numpy 2 the devkit's render_ego_centric_map calls int() on a
        # one-element array, which numpy 2 refuses (docs/nuscenes.md)
        extra = {} if channel.startswith("CAM") else {"underlay_map": False}
        path = tmp_path / f"{channel}.png"
        nusc.render_sample_data(sample["data"][channel], out_path=str(path), verbose=False, **extra)
        assert path.stat().st_size > 10_000
        matplotlib.pyplot.close("all")


def _iou(a, b) -> float:
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def test_the_devkits_boxes_project_where_hydrabenchs_labels_are(export):
    data, _, _, nusc = export
    reader = DatasetReader(data)
    compared, visible_ious = 0, []
    for sample in nusc.sample:
        i = sample["hydrabench"]["frame"]
        meta, labels = reader.meta(i), reader.labels(i)
        calib = Calibration.from_dict(meta["calibration"])
        for channel, camera in (("CAM_FRONT", "camera_right"), ("CAM_FRONT_STEREO_LEFT", "camera_left")):
            _, boxes, K = nusc.get_sample_data(sample["data"][channel], box_vis_level=BoxVisibility.ANY)
            ref = reference_labels(labels["objects"], calib, camera, 1e9)
            ref_box = dict(zip(ref["ids"], ref["boxes"]))
            fwd = labels[camera]
            cam = calib.camera(camera)
            for box in boxes:
                corners = box.corners()
                if corners[2].min() <= 0.1:  # reaches behind the near plane: the devkit does not clip
                    continue
                uv = view_points(corners, K, normalize=True)
                hull = [max(uv[0].min(), 0), max(uv[1].min(), 0), min(uv[0].max(), cam.width),
                        min(uv[1].max(), cam.height)]
                aid = nusc.get("sample_annotation", box.token)["hydrabench"]["actor_id"]
                assert _iou(hull, ref_box[aid]) > 0.99, (channel, aid, hull, ref_box[aid])
                compared += 1
                if aid in fwd["ids"]:
                    k = fwd["ids"].index(aid)
                    if fwd["occlusion"][k] < 0.1 and fwd["truncation"][k] == 0 and not fwd["difficult"][k]:
                        visible_ious.append(_iou(hull, fwd["boxes"][k]))
    assert compared >= 10 and len(visible_ious) >= 3
    # the visible-pixel box of an unoccluded object lies inside its 3D box's hull and fills most of it
    assert min(visible_ious) > 0.5, visible_ious


def test_each_log_has_a_map_with_the_ego_on_the_road(export):
    _, _, _, nusc = export
    for sd in nusc.sample_data:
        if sd["channel"] != "LIDAR_TOP":
            continue
        pose = nusc.get("ego_pose", sd["ego_pose_token"])
        scene = nusc.get("scene", nusc.get("sample", sd["sample_token"])["scene_token"])
        mask = nusc.get("map", nusc.get("log", scene["log_token"])["map_token"])["mask"]
        assert mask.is_on_mask(pose["translation"][0], pose["translation"][1])[0]
        assert 0.05 < (mask.mask() > 0).mean() < 0.8  # a road, not an empty or a full image


def test_the_splits_are_hydrabenchs_and_the_devkit_reads_them(export):
    data, _, summary, nusc = export
    splits = hydrabench_splits(data)
    for name in SPLIT_NAMES:
        assert get_scenes_of_split(name, nusc) == [ns.scene_name(s) for s in splits[name]]
    train, test = set(splits["hydrabench-train"]), set(splits["hydrabench-test"])
    assert train and test and not train & test and train | test == set(splits["hydrabench-all"])
    assert summary["split_scenes"]["hydrabench-all"] == len(nusc.scene)
    from fusion.data import split_by_sequence  # what a training run splits by

    reader = DatasetReader(data)
    for seed in (0, 1, 2):
        _, test_frames = split_by_sequence(reader, 0.7, seed)
        assert hydrabench_splits(data, split_seed=seed)["hydrabench-test"] == sorted(
            {reader.index[i][0] for i in test_frames})


def _evaluate(out, nusc, results, tmp_path):
    path = tmp_path / "results.json"
    path.write_text(json.dumps(results))
    ev = DetectionEval(nusc, config_factory("detection_cvpr_2019"), str(path), "hydrabench-all",
                       str(tmp_path / "eval"), verbose=False)
    metrics, _ = ev.evaluate()
    return ev, metrics


def _scored(nusc, cfg) -> dict:
    """Per detection name, the annotations DetectionEval scores, counted from the tables: at least one
    lidar or radar point, and the box centre within the class's range of the LIDAR_TOP ego pose."""
    det = {c: d for c, d in ns.CLASS_TABLE.values()}
    out = {}
    for a in nusc.sample_annotation:
        sample = nusc.get("sample", a["sample_token"])
        pose = nusc.get("ego_pose", nusc.get("sample_data", sample["data"]["LIDAR_TOP"])["ego_pose_token"])
        name = det[a["category_name"]]
        dist = math.hypot(a["translation"][0] - pose["translation"][0], a["translation"][1] - pose["translation"][1])
        if a["num_lidar_pts"] + a["num_radar_pts"] > 0 and dist < cfg.class_range[name]:
            out.setdefault(name, set()).add(a["token"])
    return out


def test_the_labels_as_results_score_ap_1_in_the_devkits_detection_eval(export, tmp_path):
    _, out, _, nusc = export
    ev, metrics = _evaluate(out, nusc, ns.results_from_labels(out), tmp_path)
    scored = _scored(nusc, ev.cfg)
    assert len(scored) >= 2 and sum(len(v) for v in scored.values()) == len(ev.gt_boxes.all)
    for name in ev.cfg.class_names:
        assert metrics.mean_dist_aps[name] == pytest.approx(1.0 if name in scored else 0.0, abs=1e-9), name
    for name in scored:  # exact boxes: no translation, scale or orientation error
        for err in ("trans_err", "scale_err", "orient_err", "attr_err"):
            assert metrics.get_label_tp(name, err) == pytest.approx(0.0, abs=1e-6), (name, err)
    # nuScenes' mAP divides by its ten classes; hydrabench makes six of them
    assert metrics.mean_ap == pytest.approx(len(scored) / 10)


def test_dropped_and_moved_boxes_score_what_that_implies(export, tmp_path):
    _, out, _, nusc = export
    drop = 0.4
    results = ns.results_from_labels(out, drop=drop, seed=3)
    ev, metrics = _evaluate(out, nusc, results, tmp_path)
    scored = _scored(nusc, ev.cfg)
    kept = {(b.sample_token, tuple(b.translation)) for b in ev.pred_boxes.all}
    grid = np.linspace(0, 1, 101)[11:]  # the devkit's recall levels above min_recall 0.1
    for name, tokens in scored.items():
        anns = [nusc.get("sample_annotation", t) for t in tokens]
        found = sum((a["sample_token"], tuple(a["translation"])) in kept for a in anns)
        assert found < len(anns) or len(anns) == 1
        # every kept box is right: precision 1 up to recall found / n, then nothing
        expected = float(np.mean(grid <= found / len(anns)))
        assert metrics.mean_dist_aps[name] == pytest.approx(expected, abs=1e-9), name
    # 1.5 m off: a hit at the 2 m and 4 m centre-distance thresholds, a miss at 0.5 m and 1 m
    ev, metrics = _evaluate(out, nusc, ns.results_from_labels(out, offset_m=1.5), tmp_path)
    for name in scored:
        assert metrics.mean_dist_aps[name] == pytest.approx(0.5), name
        assert metrics.get_label_tp(name, "trans_err") == pytest.approx(1.5, abs=1e-6)


def test_quaternions_and_radar_files_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        np.testing.assert_allclose(ns.quaternion_from_matrix(R), q * np.sign(w), atol=1e-8)
    # a target in a noise floor: one peak at its cell, its rcs from the radar equation
    polar = np.full((400, 288), 20, np.uint8)  # 0 dB: the noise power
    polar[100, 150] = 120  # 50 dB above
    pts = ns.radar_points(polar, 0.3472)
    assert len(pts) == 1
    r, phi = 150.5 * 0.3472, 2 * np.pi * 100 / 400
    np.testing.assert_allclose([pts["x"][0], pts["y"][0]], [r * np.cos(phi), r * np.sin(phi)], rtol=1e-6)
    assert pts["dyn_prop"][0] == ns.DYN_PROP_UNKNOWN and pts["vx"][0] == 0
    empty = ns.radar_points(np.full((400, 288), 20, np.uint8), 0.3472)
    assert len(empty) == 0
    for name, points in (("one.pcd", pts), ("empty.pcd", empty)):
        (tmp_path / name).write_bytes(ns.radar_pcd_bytes(points))
        cloud = RadarPointCloud.from_file(str(tmp_path / name))
        assert cloud.points.shape == (18, len(points))
        np.testing.assert_array_equal(ns.read_radar_pcd(tmp_path / name), points)
