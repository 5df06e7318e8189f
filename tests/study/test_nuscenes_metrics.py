"""hydrabench score --nuscenes-metrics: the nuScenes devkit's own detection evaluation (study.experiments.nuscenes_metrics)
beside VOC mAP@0.5: the labels written back score 1 overall, per context and per severity; a known share
dropped scores what its recall cap implies; and on the boxes both metrics count, both find the same true
positives."""

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from nuscenes.eval.common.config import config_factory

from fusion.protocol import frame_labels
from sensors.dataset import DatasetReader
from sensors.export.nuscenes import CLASS_TABLE, load_tables, results_from_labels
from sensors.generate import GenerateConfig
from study.cli import main
from study.experiments.external import merge_labels
from study.experiments.nuscenes_metrics import CONFIG, open_export

# the config tests/study/test_external.py and test_export_nuscenes.py use: no new dataset
CONFIG_DATA = GenerateConfig(contexts=("junction", "fog"), frames_per_context=4, sequence_length=2, seed=9)
GRID = np.linspace(0, 1, 101)[11:]  # the devkit's recall levels above its min_recall 0.1
DETECTION_NAME = {c: d for c, (_, d) in CLASS_TABLE.items()}  # RADIATE class -> detection name


@pytest.fixture(scope="module")
def world(shared_nuscenes_export):
    data, out = shared_nuscenes_export(CONFIG_DATA)
    nusc = open_export(out)
    return SimpleNamespace(data=data, out=out, nusc=nusc, reader=DatasetReader(data), cfg=config_factory(CONFIG))


def _score(capsys, world, path, *args):
    code = main(["score", str(world.data), "--export", str(world.out), "--nuscenes", f"lidar={path}",
                 "--nuscenes-metrics", "--bootstrap", "0", *map(str, args)])
    out, err = capsys.readouterr()
    return SimpleNamespace(returncode=code, stdout=out, stderr=err, json=json.loads(out) if code == 0 and "--json" in args
                           else None)


def _write(path, doc) -> str:
    path.write_text(json.dumps(doc))
    return str(path)


def _lidar(doc):
    doc["meta"].update(use_lidar=True, use_camera=False, use_radar=False)
    return doc


def _devkit_scored(world) -> set:
    """Annotation tokens the devkit scores: at least one lidar or radar point, centre within the class's
    range of the LIDAR_TOP ego pose (its filter_eval_boxes, counted from the tables)."""
    nusc, out = world.nusc, set()
    for a in nusc.sample_annotation:
        sample = nusc.get("sample", a["sample_token"])
        pose = nusc.get("ego_pose", nusc.get("sample_data", sample["data"]["LIDAR_TOP"])["ego_pose_token"])
        name = DETECTION_NAME[a["hydrabench"]["class"]]
        dist = math.hypot(a["translation"][0] - pose["translation"][0], a["translation"][1] - pose["translation"][1])
        if a["num_lidar_pts"] + a["num_radar_pts"] > 0 and dist < world.cfg.class_range[name]:
            out.add(a["token"])
    return out


def _frame_of(world) -> dict:
    return {s["token"]: s["hydrabench"]["frame"] for s in world.nusc.sample}


def test_the_labels_written_back_score_1_overall_per_context_and_per_severity(world, tmp_path, capsys):
    p = _score(capsys, world, _write(tmp_path / "labels.json", _lidar(results_from_labels(world.out))), "--json")
    assert p.returncode == 0, p.stderr
    ns = p.json["methods"]["single:lidar"]["nuscenes"]
    assert p.json["nuscenes_metrics"]["config"] == CONFIG and ns["fields"] == {"velocity": True, "attribute": True}
    subsets = [ns["overall"], *ns["per_context"].values(), *ns["per_severity"].values()]
    assert set(ns["per_context"]) == {"junction", "fog"} and len(ns["per_severity"]) >= 3
    for s in subsets:
        assert s["classes"] and s["map"] == 1.0 and set(s["ap_per_class"].values()) == {1.0}, s
        # exact boxes: no translation, scale, orientation or attribute error
        assert s["tp_errors"]["mATE"] == s["tp_errors"]["mASE"] == s["tp_errors"]["mAOE"] == s["tp_errors"]["mAAE"] == 0
        # the devkit's ground-truth velocity is a finite difference over neighbouring samples, the labels'
        # the actor's own: they differ where an actor accelerates, and NDS says by how much
        ave = s["tp_errors"]["mAVE"]
        assert s["nds"] == pytest.approx((5 + 4 + 1 - min(1, ave)) / 10, abs=2e-4)
        # the devkit's own mean is over its ten classes, of which the export has these
        assert s["devkit"]["mean_ap"] == pytest.approx(len(s["classes"]) / 10, abs=1e-4)
    counted = sum(ns["overall"]["ground_truth_per_class"].values())
    assert counted == len(_devkit_scored(world)) > 5
    assert ns["per_context"]["fog"]["frames"] + ns["per_context"]["junction"]["frames"] == ns["overall"]["frames"] == 8
    p = _score(capsys, world, _write(tmp_path / "labels.json", _lidar(results_from_labels(world.out))))
    assert p.returncode == 0 and "nuScenes devkit (detection_cvpr_2019)" in p.stdout and "NDS" in p.stdout


def test_a_known_share_dropped_scores_what_its_recall_cap_implies(world, tmp_path, capsys):
    doc = _lidar(results_from_labels(world.out, drop=0.4, seed=3))
    p = _score(capsys, world, _write(tmp_path / "drop.json", doc), "--json")
    assert p.returncode == 0, p.stderr
    ns = p.json["methods"]["single:lidar"]["nuscenes"]
    scored, frame_of = _devkit_scored(world), _frame_of(world)
    kept = {(b["sample_token"], tuple(b["translation"])) for boxes in doc["results"].values() for b in boxes}
    metas = {f: world.reader.meta(f) for f in frame_of.values()}
    groups = {"overall": lambda m: True, **{c: (lambda m, c=c: m["context"] == c) for c in ns["per_context"]}}
    for group, member in groups.items():
        found, total = {}, {}
        for a in world.nusc.sample_annotation:
            if a["token"] in scored and member(metas[frame_of[a["sample_token"]]]):
                name = DETECTION_NAME[a["hydrabench"]["class"]]
                total[name] = total.get(name, 0) + 1
                found[name] = found.get(name, 0) + ((a["sample_token"], tuple(a["translation"])) in kept)
        s = ns["overall"] if group == "overall" else ns["per_context"][group]
        # every kept box is right at score 1: precision 1 up to recall found / total, then nothing
        expect = {n: float(np.mean(GRID <= found[n] / total[n])) for n in total}
        assert s["ap_per_class"] == pytest.approx(expect, abs=1e-4), group
        assert s["map"] == pytest.approx(np.mean(list(expect.values())), abs=1e-4) and s["map"] < 1.0, group
        assert s["ground_truth_per_class"] == total


def _both_count(world) -> dict:
    """Per detection name, the annotations of objects both metrics count: the devkit (range, a lidar or
    radar point) and hydrabench's reference protocol in the right camera (not difficult)."""
    scored, frame_of, out = _devkit_scored(world), _frame_of(world), {}
    counted = {}
    for f in set(frame_of.values()):
        meta = dict(world.reader.meta(f), dataset_index=f)
        lab = frame_labels(merge_labels(world.reader.labels(f)), meta, "reference")["camera_right"]
        counted[f] = {a for a, d in zip(lab["ids"], lab["difficult"]) if not d}
    for a in load_tables(world.out)["sample_annotation"]:
        if a["token"] in scored and a["hydrabench"]["actor_id"] in counted[frame_of[a["sample_token"]]]:
            out.setdefault(DETECTION_NAME[a["hydrabench"]["class"]], []).append(a)
    return out


def test_on_the_boxes_both_count_both_metrics_find_the_same_true_positives(world, tmp_path, capsys):
    both = _both_count(world)
    assert sum(map(len, both.values())) > 5 and len(both) >= 2
    results = {s["token"]: [] for s in world.nusc.sample}
    kept = {}
    for name, anns in both.items():  # every third object of each class left out
        for j, a in enumerate(anns):
            if j % 3 == 0:
                continue
            kept[name] = kept.get(name, 0) + 1
            results[a["sample_token"]].append({"sample_token": a["sample_token"], "translation": a["translation"],
                                               "size": a["size"], "rotation": a["rotation"], "velocity": [0.0, 0.0],
                                               "detection_name": name, "detection_score": 1.0,
                                               "attribute_name": ""})
    doc = {"meta": {"use_camera": False, "use_lidar": True, "use_radar": False, "use_map": False,
                    "use_external": False}, "results": results}
    p = _score(capsys, world, _write(tmp_path / "both.json", doc), "--json")
    assert p.returncode == 0, p.stderr
    row = p.json["methods"]["single:lidar"]
    voc = {DETECTION_NAME[c]: ap for c, ap in row["ap_per_class"].items() if ap is not None}
    voc_positives = {DETECTION_NAME[c]: n for c, n in row["positives_per_class"].items() if n}
    dev = row["nuscenes"]["overall"]
    for name in both:
        # hydrabench: VOC AP at precision 1 is the recall, so AP x positives is the true positives it found
        assert round(voc[name] * voc_positives[name]) == kept.get(name, 0), name
        # the devkit: the AP its recall grid gives that many true positives among its own ground truth
        n = dev["ground_truth_per_class"][name]
        assert dev["ap_per_class"][name] == pytest.approx(np.mean(GRID <= kept.get(name, 0) / n), abs=1e-4), name
        assert dev["ground_truth_per_class"][name] >= len(both[name]) and voc_positives[name] >= len(both[name])
    # no velocity or attribute in the file: no mAAE, no NDS from present classes (the devkit's own still there)
    assert row["nuscenes"]["fields"] == {"velocity": True, "attribute": False}
    assert dev["tp_errors"]["mAAE"] is None and dev["nds"] is None and dev["devkit"]["nd_score"] is not None


def test_what_the_devkit_needs_is_checked_by_file_and_record(world, tmp_path, capsys):
    good = _lidar(results_from_labels(world.out))
    token = next(t for t, boxes in good["results"].items() if boxes)
    for field, value, words in (("velocity", [1.0], "velocity must be [vx, vy]"),
                                ("attribute_name", "vehicle.flying", "attribute_name must be a nuScenes attribute")):
        doc = json.loads(json.dumps(good))
        doc["results"][token][0][field] = value
        path = _write(tmp_path / f"{field}.json", doc)
        p = _score(capsys, world, path)
        assert p.returncode == 2 and words in p.stderr and path in p.stderr and f"results['{token}'][0]" in p.stderr
        assert len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr
    coco = _write(tmp_path / "coco.json", [])
    code = main(["score", str(world.data), "--coco", coco, "--nuscenes-metrics", "--bootstrap", "0"])
    err = capsys.readouterr().err
    assert code == 2 and "--nuscenes-metrics: the devkit scores 3D boxes" in err
