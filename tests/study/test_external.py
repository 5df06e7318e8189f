"""hydrabench score: detections from outside (nuScenes and COCO results) read into the right camera and
scored by the one path; damaged files refused by file and record; a selection file scored as a gate;
round trips through the nuScenes export."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

from fusion.late import to_reference
from fusion.metrics import box_iou
from sensors.dataset import DatasetReader
from sensors.export.nuscenes import load_tables, results_from_labels
from sensors.generate import GenerateConfig
from sensors.rig import Calibration
from study.cli import main
from study.engine.scoring import fused, ground_truth, score
from study.experiments.external import (
    ExportIndex,
    MergedReader,
    bev_results,
    coco_results,
    load_external,
    merge_detections,
    merge_labels,
    score_external,
)
from study.experiments.nuscenes_export import export_nuscenes

# the config tests/study/test_export_nuscenes.py uses: no new dataset
CONFIG = GenerateConfig(contexts=("junction", "fog"), frames_per_context=4, sequence_length=2, seed=9)


@pytest.fixture(scope="module")
def export(shared_dataset, tmp_path_factory):
    data = shared_dataset(CONFIG)
    out = tmp_path_factory.mktemp("ns") / "export"
    export_nuscenes(data, out, progress=False)
    return data, out


def _write(path, doc):
    path.write_text(json.dumps(doc))
    return str(path)


def _counted(reader, meta):
    """Actor ids the reference protocol counts (not difficult) in the right camera, with their classes."""
    i = meta["dataset_index"]
    labels = merge_labels(reader.labels(i))
    from fusion.protocol import frame_labels

    lab = frame_labels(labels, dict(reader.meta(i), dataset_index=i), "reference")["camera_right"]
    return {a: c for a, c, d in zip(lab["ids"], lab["labels"], lab["difficult"]) if not d}


def _protocol_results(out, reader, drop_every=0):
    """Every annotation of an actor the reference protocol counts in the right camera, as results
    (score 1); `drop_every` k > 0 leaves out every k-th of them per detection name."""
    full = results_from_labels(out)
    t = load_tables(out)
    frame_of = {s["token"]: s["hydrabench"]["frame"] for s in t["sample"]}
    by_name = {}
    results = {tok: [] for tok in full["results"]}
    for a in t["sample_annotation"]:
        f = frame_of[a["sample_token"]]
        if a["hydrabench"]["actor_id"] in _counted(reader, dict(reader.meta(f), dataset_index=f)):
            name = {"van": "car", "group_of_pedestrians": "pedestrian"}.get(a["hydrabench"]["class"],
                                                                           a["hydrabench"]["class"])
            name = {"motorbike": "motorcycle"}.get(name, name)
            by_name.setdefault(name, []).append(a)
    kept = {}
    for name, anns in by_name.items():
        for j, a in enumerate(anns):
            if drop_every and j % drop_every == 0:
                continue
            kept[name] = kept.get(name, 0) + 1
            results[a["sample_token"]].append({"sample_token": a["sample_token"], "translation": a["translation"],
                                               "size": a["size"], "rotation": a["rotation"],
                                               "velocity": [0.0, 0.0], "detection_name": name,
                                               "detection_score": 1.0, "attribute_name": ""})
    meta = {"use_camera": False, "use_lidar": True, "use_radar": False, "use_map": False, "use_external": False}
    return {"meta": meta, "results": results}, kept, {n: len(a) for n, a in by_name.items()}


def test_the_labels_read_back_are_the_protocols_boxes_and_score_ap_1(export, tmp_path):
    data, out = export
    reader = DatasetReader(data)
    doc, kept, total = _protocol_results(out, reader)
    assert kept == total and sum(total.values()) > 5
    ext, _ = load_external(reader, nuscenes=[_write(tmp_path / "r.json", doc)], export=out)
    for meta, per in ext.per_frame:  # each box lands on its ground-truth box
        g = ground_truth(merge_labels(reader.labels(meta["dataset_index"])), "camera_right", None, meta, "reference")
        d = per["lidar"]
        keep = ~g["difficult"]
        assert len(d) == keep.sum()
        if len(d):
            assert box_iou(d.boxes, g["boxes"][keep]).max(axis=1).min() > 0.999
    r = score_external(reader, ext, resamples=0)
    assert r["methods"]["single:lidar"]["map"] == 1.0
    # the devkit's own results_from_labels writes boxes the protocol does not count (beyond its range,
    # or the right camera's): false positives at score 1, so it scores below 1 here
    full = results_from_labels(out)
    full["meta"]["use_radar"] = True
    ext2, _ = load_external(reader, nuscenes=[_write(tmp_path / "full.json", full)], export=out)
    assert score_external(reader, ext2, resamples=0)["methods"]["single:radar"]["map"] < 1.0


def test_a_known_share_dropped_scores_what_it_implies(export, tmp_path):
    data, out = export
    reader = DatasetReader(data)
    doc, kept, total = _protocol_results(out, reader, drop_every=3)
    ext, _ = load_external(reader, nuscenes=[_write(tmp_path / "r.json", doc)], export=out)
    r = score_external(reader, ext, resamples=0)["methods"]["single:lidar"]
    # every detection is a true positive at score 1: precision 1 up to recall kept / total, so AP = that
    expect = {n: kept.get(n, 0) / total[n] for n in total}
    assert r["map"] == pytest.approx(np.mean(list(expect.values())), abs=1e-4)
    assert r["map"] < 1.0


def test_the_own_networks_predictions_exported_and_read_back_score_the_same(export, tmp_path):
    from study.engine import reference_model as rm
    from study.engine.predictions import predict

    data, out = export
    reader = DatasetReader(data)
    pred = predict(rm.resolve_run("cpu-frontier"), data, tmp_path / "pred", gates=("knowledge",), split="all",
                   progress=False)
    index = ExportIndex(out, reader)
    per_frame = [(dict(reader.meta(m["dataset_index"]), dataset_index=m["dataset_index"]), per)
                 for m, per in pred.per_frame]
    frames = pred.branch_frames
    bev = [b for b in pred.branches if frames[b] == "bev"]
    files = [f"{b}={_write(tmp_path / f'{b}.json', bev_results(per_frame, b, index, pred.branch_sensors[b]))}"
             for b in bev]
    coco = [f"camera_right={_write(tmp_path / 'cam.json', coco_results(per_frame, 'camera_right'))}"]
    ext, _ = load_external(reader, nuscenes=files, coco=coco, export=out)
    merged_reader = MergedReader(reader)
    # the own path: each branch mapped into the right camera (Appendix A with its own class heights),
    # then scored in the merged classes nuScenes names tell apart
    merged = [(m, {b: merge_detections(to_reference(d, frames[b], Calibration.from_dict(m["calibration"])))
                   for b, d in per.items()}) for m, per in per_frame]
    in_camera = {b: "camera_right" for b in frames}
    for b in [*bev, "camera_right"]:
        own = score(fused(merged, [b], in_camera, "soft_nms"), merged_reader, protocol="reference")
        back = score_external(reader, ext, resamples=0)["methods"][f"single:{b}"]
        assert back["map"] == pytest.approx(own["map"], abs=1e-9), b
        assert back["map_per_context"] == own["map_per_context"], b
    assert sum(len(per["camera_right"]) for _, per in merged) > 0
    assert sum(len(ext.per_frame[k][1][b]) for k in range(len(ext.per_frame)) for b in bev) > 0


def _hb(capsys, *args):
    """`hydrabench score ARGS` in this process: its exit code, stdout and stderr."""
    code = main(["score", *map(str, args)])
    out, err = capsys.readouterr()
    return SimpleNamespace(returncode=code, stdout=out, stderr=err)


def test_damaged_files_are_refused_with_one_line_naming_the_file_and_record(export, tmp_path, capsys):
    data, out = export
    good = results_from_labels(out)
    good["meta"]["use_lidar"] = True
    token = next(t for t, boxes in good["results"].items() if boxes)

    def damaged(name, change):
        doc = json.loads(json.dumps(good))
        change(doc)
        return _write(tmp_path / f"{name}.json", doc)

    cases = {
        "nan": (lambda d: d["results"][token][0].__setitem__("size", [float("nan"), 1, 1]), "size"),
        "negative": (lambda d: d["results"][token][0].__setitem__("size", [-1, 1, 1]), "size"),
        "nometa": (lambda d: d.pop("meta"), "no 'meta'"),
        "cls": (lambda d: d["results"][token][0].__setitem__("detection_name", "tram"), "'tram'"),
        "unknown": (lambda d: d["results"].__setitem__("f" * 32, []), "unknown sample token"),
        "other": (lambda d: d.__setitem__("results", {"a" * 32: []}), "another dataset"),
        "left": (lambda d: d["results"].pop(token), "leaves out 1"),
    }
    for name, (change, words) in cases.items():
        path = damaged(name, change)
        p = _hb(capsys, data, "--export", out, "--nuscenes", path, "--bootstrap", "0")
        assert p.returncode == 2 and words in p.stderr and path in p.stderr, (name, p.stderr)
        assert len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr, name
    text = json.dumps(good)
    twice = text[:-2] + f', "{token}": []' + text[-2:]  # the same sample token twice in "results"
    (tmp_path / "twice.json").write_text(twice)
    p = _hb(capsys, data, "--export", out, "--nuscenes", tmp_path / "twice.json", "--bootstrap", "0")
    assert p.returncode == 2 and "appears twice" in p.stderr and token in p.stderr
    # a frame left out, scored as empty when asked, and counted
    p = _hb(capsys, data, "--export", out, "--nuscenes", tmp_path / "left.json", "--missing", "empty", "--bootstrap", "0",
            "--json")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["left_out_frames_scored_empty"] == {"lidar": 1}
    bad_coco = _write(tmp_path / "coco.json", [{"image_id": 999, "category_id": 1, "bbox": [0, 0, 5, 5],
                                                "score": 0.5}])
    p = _hb(capsys, data, "--coco", bad_coco, "--bootstrap", "0")
    assert p.returncode == 2 and "record 0" in p.stderr and "image_id 999" in p.stderr


def test_a_selection_file_is_scored_as_a_gate_with_intervals(export, tmp_path, capsys):
    data, out = export
    reader = DatasetReader(data)
    doc, _, _ = _protocol_results(out, reader)
    lidar = _write(tmp_path / "lidar.json", doc)
    half, _, _ = _protocol_results(out, reader, drop_every=2)
    half["meta"] = {**half["meta"], "use_lidar": False, "use_radar": True}
    radar = _write(tmp_path / "radar.json", half)
    tokens = list(doc["results"])
    sel_lidar = _write(tmp_path / "g1.json", {t: ["lidar"] for t in tokens})
    # keys may be frame indices too
    sel_radar = _write(tmp_path / "g2.json", {str(i): ["radar"] for i in range(len(reader))})
    p = _hb(capsys, data, "--export", out, "--nuscenes", lidar, "--nuscenes", radar, "--selection", f"pick={sel_lidar}",
            "--selection", f"other={sel_radar}", "--bootstrap", "20", "--json")
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    m = r["methods"]
    assert m["selection:pick"]["map"] == m["single:lidar"]["map"] == 1.0
    assert m["selection:other"]["map"] == m["single:radar"]["map"] < 1.0
    assert set(m) == {"single:lidar", "single:radar", "late", "selection:pick", "selection:other", "context_oracle"}
    assert m["selection:other"]["minus_late"]["ci95"] is not None
    # the context oracle (a bound): per context the best of the fixed configurations on these frames
    oracle = r["context_oracle"]
    assert set(oracle["candidates"]) == {"single:lidar", "single:radar", "late"} and "bound" in oracle["chosen_on"]
    for c in r["contexts"]:
        best = max(m[k]["map_per_context"][c] for k in oracle["candidates"])
        assert m[oracle["choice"][c]]["map_per_context"][c] == best
        assert m["context_oracle"]["map_per_context"][c] == pytest.approx(best, abs=1e-9)
    assert "not a method" in m["context_oracle"]["kind"] and "optimistic" in m["context_oracle"]["kind"]
    room = oracle["room_corrected"]
    assert room["reference"] == "late" and room["naive"]["estimate"] >= 0
    assert set(m["selection:pick"]["ci95_per_context"]) == set(r["contexts"])
    bad = _write(tmp_path / "g3.json", {tokens[0]: ["sonar"]})
    p = _hb(capsys, data, "--export", out, "--nuscenes", lidar, "--selection", bad, "--bootstrap", "0")
    assert p.returncode == 2 and "unknown branch 'sonar'" in p.stderr and bad in p.stderr
