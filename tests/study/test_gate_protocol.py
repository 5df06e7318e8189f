"""hydrabench score --gate: gates from outside (study.experiments.gate_protocol, docs/nuscenes.md) loaded by module path or
entry point, read only what a car measures and the detections, and are scored exactly as the selection file
of their choice; every broken return or import is one line naming the gate and the frame."""

import importlib.metadata
import json
from dataclasses import fields
from types import SimpleNamespace

import numpy as np
import pytest

from sensors.dataset import DatasetReader
from sensors.export.nuscenes import results_from_labels
from sensors.generate import GenerateConfig
from study.cli import main
from study.engine.scoring import fuse_selection
from study.experiments.external import ExportIndex, load_external, read_selection, score_external
from study.experiments.gate_protocol import (
    ENTRY_POINT_GROUP,
    WEATHER_READINGS,
    GateFrame,
    gate_selection,
    load_gate,
)
from tests.study.data import example_gates

# the config tests/study/test_external.py and test_export_nuscenes.py use: no new dataset
CONFIG = GenerateConfig(contexts=("junction", "fog"), frames_per_context=4, sequence_length=2, seed=9)
GATES = "tests.study.data.example_gates"


@pytest.fixture(scope="module")
def world(shared_nuscenes_export, tmp_path_factory):
    """The dataset, its export, and three branches' nuScenes results: the export's labels, 40 % of each
    class left out at random, another share for each branch."""
    data, out = shared_nuscenes_export(CONFIG)
    box = tmp_path_factory.mktemp("gates")
    specs = []
    for name, seed in (("lidar", 0), ("radar", 1), ("camera", 2)):
        doc = results_from_labels(out, drop=0.4, seed=seed)
        doc["meta"].update(use_lidar=name == "lidar", use_radar=name == "radar", use_camera=name == "camera")
        (box / f"{name}.json").write_text(json.dumps(doc))
        specs.append(f"{name}={box / f'{name}.json'}")
    return SimpleNamespace(data=data, out=out, box=box, nuscenes=specs)


def _hb(capsys, world, *args):
    argv = ["score", str(world.data), "--export", str(world.out)]
    for spec in world.nuscenes:
        argv += ["--nuscenes", spec]
    code = main([*argv, *map(str, args)])
    out, err = capsys.readouterr()
    return SimpleNamespace(returncode=code, stdout=out, stderr=err, json=json.loads(out) if code == 0 and out.startswith("{") else None)


def _selection_file(path, choices: dict) -> str:
    path.write_text(json.dumps({str(f): list(c) for f, c in choices.items()}))
    return str(path)


def _same_row(a: dict, b: dict):
    a, b = dict(a), dict(b)
    a.pop("kind"), b.pop("kind")
    assert a == b


def test_a_gate_scores_exactly_as_the_selection_file_of_its_choice(world, tmp_path, capsys):
    reader = DatasetReader(world.data)
    fog = {i: reader.meta(i)["weather"]["visibility_m"] < example_gates.FOG_VISIBILITY_M for i in range(len(reader))}
    assert 0 < sum(fog.values()) < len(fog)  # the rule chooses differently on different frames
    choices = {i: ("radar",) if fog[i] else ("lidar", "radar", "camera") for i in fog}
    sel = _selection_file(tmp_path / "sel.json", choices)
    p = _hb(capsys, world, "--gate", f"{GATES}:by_visibility", "--selection", f"file={sel}", "--bootstrap", "20",
            "--json")
    assert p.returncode == 0, p.stderr
    m = p.json["methods"]
    _same_row(m["gate:by_visibility"], m["selection:file"])
    assert m["gate:by_visibility"]["ci95"] is not None and m["gate:by_visibility"]["minus_late"]["ci95"] is not None
    assert m["gate:by_visibility"]["map_per_context"]["fog"] == m["single:radar"]["map_per_context"]["fog"]
    assert m["gate:by_visibility"]["branch_share"]["radar"] == 1.0
    assert m["gate:by_visibility"]["branch_share"]["lidar"] == pytest.approx(1 - sum(fog.values()) / len(fog))
    # its sensors' energy per frame is the mean of what each frame's choice reads (clock gating)
    e = {k: m[f"single:{k}"]["sensor_energy_j"] for k in ("radar",)}
    all_three = m["late"]["sensor_energy_j"]
    expect = np.mean([e["radar"] if fog[i] else all_three for i in fog])
    assert m["gate:by_visibility"]["sensor_energy_j"] == pytest.approx(expect, abs=1e-4)
    assert p.json["gates"]["by_visibility"]["spec"] == f"{GATES}:by_visibility"
    # the same through the library, unrounded: the same per-frame selection, the same fused boxes
    ext, index = load_external(reader, nuscenes=world.nuscenes, export=world.out)
    name, gate = load_gate(f"{GATES}:by_visibility")
    from_gate = gate_selection(name, gate, ext, index)
    from_file = read_selection(sel, ext, index)
    assert from_gate == from_file
    frames = {b: "camera_right" for b in ext.branches}
    for (_, a), (_, b) in zip(fuse_selection(ext.per_frame, from_gate, frames, "soft_nms"),
                              fuse_selection(ext.per_frame, from_file, frames, "soft_nms"), strict=True):
        np.testing.assert_allclose(a.boxes, b.boxes, atol=1e-12)
        np.testing.assert_allclose(a.scores, b.scores, atol=1e-12)
    r = score_external(reader, ext, selections={"file": from_file}, gates={"g": from_gate}, resamples=0)
    _same_row(r["methods"]["gate:g"], r["methods"]["selection:file"])


def _top_k(ext, k):
    """Per frame, the k branches with the highest summed confidence (ties: branch order), in branch order."""
    out = {}
    for meta, per in ext.per_frame:
        s = np.array([per[b].scores.sum() for b in ext.branches])
        keep = sorted(np.argsort(-s, kind="stable")[:k])
        out[meta["dataset_index"]] = tuple(ext.branches[j] for j in keep)
    return out


def test_a_score_returning_gate_is_its_top_k(world, tmp_path, capsys):
    reader = DatasetReader(world.data)
    ext, index = load_external(reader, nuscenes=world.nuscenes, export=world.out)
    name, gate = load_gate(f"most={GATES}:MostConfident")
    assert name == "most" and isinstance(gate, example_gates.MostConfident)
    assert gate_selection(name, gate, ext, index, k=1) == [_top_k(ext, 1)[m["dataset_index"]] for m, _ in ext.per_frame]
    assert gate.seen == sorted(gate.seen) == [m["dataset_index"] for m, _ in ext.per_frame]  # once each, in order
    for k_arg, k in ((None, 2), ("1", 1), ("all", 3)):  # default: 2, as compare's built-in gates
        sel = _selection_file(tmp_path / f"top{k}.json", _top_k(ext, k))
        extra = ["--k", k_arg] if k_arg else []
        p = _hb(capsys, world, "--gate", f"{GATES}:MostConfident", "--selection", f"top={sel}", *extra,
                "--bootstrap", "0", "--json")
        assert p.returncode == 0, p.stderr
        m = p.json["methods"]
        _same_row(m["gate:MostConfident"], m["selection:top"])
        assert m["gate:MostConfident"]["branches_per_frame"] == k
    assert len(set(_top_k(ext, 1).values())) > 1  # the scores pick different branches on different frames


def test_a_gate_reads_what_a_car_measures_and_the_detections(world):
    reader = DatasetReader(world.data)
    ext, index = load_external(reader, nuscenes=world.nuscenes, export=world.out)
    example_gates.SEEN.clear()
    name, gate = load_gate(f"{GATES}:recorder")
    gate_selection(name, gate, ext, index)
    seen = example_gates.SEEN
    assert [f.index for f in seen] == list(range(len(reader)))
    assert {f.name for f in fields(GateFrame)} == {"index", "sample_token", "sequence", "time_s", "road", "weather",
                                                   "light", "calibration", "detections", "branch_sensors"}
    tokens = ExportIndex(world.out, reader).token_of
    for f, (meta, per) in zip(seen, ext.per_frame, strict=True):
        assert f.sample_token == tokens[f.index] and f.road == meta["layout"] and f.sequence == meta["sequence_id"]
        assert dict(f.weather) == {q: meta["weather"][q] for q in WEATHER_READINGS}
        assert "severity" not in repr(f) and "context" not in repr(f) and "lens" not in repr(f)
        assert f.branches == ("lidar", "radar", "camera") and f.branch_sensors["radar"] == ("radar",)
        for b in f.branches:
            np.testing.assert_array_equal(f.detections[b].boxes, per[b].boxes)
            with pytest.raises(ValueError):  # read-only: a gate cannot change what is scored
                f.detections[b].scores[...] = 0
    assert len({f.sequence for f in seen}) == 4 and seen[1].time_s > seen[0].time_s
    # without --export there is no sample token
    from study.experiments.external import coco_results

    (world.box / "coco.json").write_text(json.dumps(coco_results(ext.per_frame, "lidar")))
    ext2, _ = load_external(reader, coco=[f"cam={world.box / 'coco.json'}"])
    example_gates.SEEN.clear()
    gate_selection(name, gate, ext2, None)
    assert example_gates.SEEN[0].sample_token is None and example_gates.SEEN[0].branches == ("cam",)


def test_a_broken_return_is_one_line_naming_the_gate_and_the_frame(world, capsys):
    cases = {
        "unknown_branch": "unknown branch 'sonar'",
        "empty_set": "an empty branch set",
        "nan_score": "the score of branch 'lidar' is nan, not a finite number",
        "missing_score": "no score for branch 'radar'",
        "wrong_type": "returned a str: 'lidar'; expected a list of branch names or a dict",
        "none_returned": "returned a NoneType",
        "twice": "branch 'lidar' named twice",
        "raises": "raised RuntimeError: the rain sensor is offline",
    }
    for attr, words in cases.items():
        p = _hb(capsys, world, "--gate", f"{GATES}:{attr}", "--bootstrap", "0")
        assert p.returncode == 2 and p.stdout == "", (attr, p.stderr)
        assert len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr, (attr, p.stderr)
        assert f"gate {attr}: frame 0:" in p.stderr and words in p.stderr, (attr, p.stderr)


def test_a_gate_that_does_not_load_is_one_line(world, capsys):
    cases = [
        (["--gate", "no_such_package.gates:pick"], "cannot import no_such_package.gates (ModuleNotFoundError"),
        (["--gate", f"{GATES}:nothing_here"], f"{GATES} has no attribute 'nothing_here'"),
        (["--gate", f"{GATES}:NOT_A_GATE"], "is a int, not a callable gate"),
        (["--gate", f"{GATES}:NeedsArguments"], "NeedsArguments() failed (TypeError"),
        (["--gate", f"{GATES}:"], "expected package.module:attr"),
        (["--gate", "x=" + f"{GATES}:by_visibility", "--gate", f"x={GATES}:MostConfident"], "two gates named 'x'"),
        (["--gate", "no-such-entry"], f"no entry point 'no-such-entry' in the group {ENTRY_POINT_GROUP}"),
        (["--gate", f"{GATES}:MostConfident", "--k", "4"], "--k: must be in 1..3"),
        (["--gate", f"{GATES}:MostConfident", "--k", "two"], "--k: expected an integer 1..3 or 'all'"),
        (["--k", "1"], "--k is for --gate"),
    ]
    for args, words in cases:
        p = _hb(capsys, world, *args, "--bootstrap", "0")
        assert p.returncode == 2 and words in p.stderr, (args, p.stderr)
        assert len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr, (args, p.stderr)


def test_a_gate_is_found_by_its_entry_point(world, capsys, monkeypatch):
    eps = [importlib.metadata.EntryPoint("visibility", f"{GATES}:by_visibility", ENTRY_POINT_GROUP),
           importlib.metadata.EntryPoint("broken", "no_such_package:gate", ENTRY_POINT_GROUP),
           importlib.metadata.EntryPoint("elsewhere", f"{GATES}:by_visibility", "other.group")]

    def entry_points(group=None):
        return [ep for ep in eps if ep.group == group]

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    p = _hb(capsys, world, "--gate", "visibility", "--gate", f"{GATES}:by_visibility", "--bootstrap", "0", "--json")
    assert p.returncode == 0, p.stderr
    _same_row(p.json["methods"]["gate:visibility"], p.json["methods"]["gate:by_visibility"])
    p = _hb(capsys, world, "--gate", "broken", "--bootstrap", "0")
    assert p.returncode == 2 and "entry point 'broken' (no_such_package:gate) does not load" in p.stderr, p.stderr
    p = _hb(capsys, world, "--gate", "elsewhere", "--bootstrap", "0")
    assert p.returncode == 2 and "(installed: broken, visibility)" in p.stderr, p.stderr
