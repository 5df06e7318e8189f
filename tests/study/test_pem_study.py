"""hydrabench pem: a PEM's predictions load and score through compare (the one scoring path), fit
reads stored predictions, and what a PEM cannot give is refused in one line. No network runs: the
first PEM is fitted on boxes drawn from the ground truth."""

import json

import numpy as np
import pytest

from sensors.generate import GenerateConfig
from sim.errors import UserError
from study.cli import main

FIT = GenerateConfig(contexts=("city", "fog"), frames_per_context=3, sequence_length=3, seed=21)
TEST = GenerateConfig(contexts=("city", "fog"), frames_per_context=3, sequence_length=3, seed=22)


def _seed_pem(run_dir, data, path):
    """A PEM file whose every branch is fitted on the ground truth moved a little (no network)."""
    from fusion.pem import FitFrame, apply_error, fit_branch
    from sensors.dataset import DatasetReader
    from study.engine.gate_data import cached_sha256, checkpoint_path
    from study.experiments.pem import FORMAT, VERSION, image_size, truth_and_features

    cfg = json.loads((run_dir / "config.json").read_text())
    specs = {s["name"]: s for s in cfg["branch_specs"]}
    reader = DatasetReader(data)
    rng = np.random.default_rng(0)
    frames = []
    for i in range(len(reader)):
        meta = dict(reader.meta(i), dataset_index=i)
        truth, table = truth_and_features(reader, meta, cfg["protocol"])
        keep = rng.random(len(truth["boxes"])) < 0.7
        boxes = apply_error(truth["boxes"], 0.03 * rng.standard_normal((len(keep), 4)))[keep]
        fa = np.array([[10.0, 10.0, 40.0, 40.0]])
        frames.append(FitFrame(np.vstack([boxes, fa]), np.r_[rng.uniform(0.5, 1, keep.sum()), 0.3],
                               np.r_[truth["labels"][keep], 1], truth, table, meta["context"], image_size(meta)))
    doc = {"format": FORMAT, "version": VERSION, "run": str(run_dir),
           "checkpoint_sha256": cached_sha256(checkpoint_path(run_dir)), "fit_data": "synthetic",
           "fit_dataset_sha256": "none", "fit_frames": len(frames), "protocol": cfg["protocol"],
           "branches": list(specs), "branch_sensors": {b: s["sensors"] for b, s in specs.items()},
           "model_frames": {b: s["frame"] for b, s in specs.items()},
           "branch_pem": {b: fit_branch(frames, s["sensors"]).to_dict() for b, s in specs.items()}}
    path.write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def setup(shared_dataset, tmp_path_factory):
    from study.engine.reference_model import resolve_run

    run_dir = resolve_run("cpu-frontier")
    fit_data, test_data = shared_dataset(FIT), shared_dataset(TEST)
    tmp = tmp_path_factory.mktemp("pem")
    _seed_pem(run_dir, fit_data, tmp / "seed.json")
    return run_dir, fit_data, test_data, tmp


def test_pem_predictions_score_through_compare(setup, capsys):
    from study.engine.predictions import load
    from study.experiments.compare import compare

    run_dir, fit_data, test_data, tmp = setup
    # draw on the fitting set, refit on those draws through the command (stored predictions, no network)
    assert main(["pem", "predict", str(tmp / "seed.json"), str(fit_data), "--out", str(tmp / "p_fit")]) == 0
    assert main(["pem", "fit", str(run_dir), str(fit_data), "--predictions", str(tmp / "p_fit"),
                 "--out", str(tmp / "pem.json"), "--json"]) == 0
    fitted = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert fitted["frames"] == 6 and set(fitted["branches"]) == {"radar", "camera_right", "lidar", "radar_lidar"}
    assert all(c["found"] > 0 and c["false_alarms"] > 0 for c in fitted["branches"].values()), fitted
    assert set(fitted["loadings"]) == set(fitted["branches"]) and all(0 <= v < 1 for v in fitted["loadings"].values())
    for out, seed in (("a", 3), ("b", 3), ("c", 4)):
        assert main(["pem", "predict", str(tmp / "pem.json"), str(test_data), "--out", str(tmp / out),
                     "--seed", str(seed)]) == 0
    a, b, c = (load(tmp / x) for x in "abc")
    assert a.gates == ["knowledge"] and a.manifest["pem"]["strength"] == 1.0
    boxes = [[d.boxes for d in per.values()] for _, per in a.per_frame]
    assert all(np.array_equal(x, y) for bx, by in zip(boxes, [[d.boxes for d in per.values()] for _, per in b.per_frame])
               for x, y in zip(bx, by))
    assert any(not np.array_equal(x.scores, y.scores) for (_, pa), (_, pc) in zip(a.per_frame, c.per_frame)
               for x, y in zip(pa.values(), pc.values()))
    # the one scoring path: compare on the stored predictions, knowledge gate and fixed methods
    r = compare(run_dir, test_data, gates=("knowledge",), resamples=20, predictions=tmp / "a", progress=False)
    assert set(r["methods"]) >= {"single:radar", "late", "all_branches", "hydrafusion:knowledge"}
    assert all(m["map"] is not None and 0 < m["map"] <= 1 for m in r["methods"].values())
    assert r["methods"]["hydrafusion:knowledge"]["minus_all_branches"]["ci95"] is not None
    # the knowledge gate ranks as the model's own gate does (from the model's frames, not camera_right)
    from fusion.nets.branch_gates import branch_quality, sensor_reliability

    meta = a.per_frame[0][0]
    assert a.predicted["knowledge"][0][1] == pytest.approx(
        1 - branch_quality(sensor_reliability(meta), ("camera_right",), "camera_right"))
    assert a.predicted["knowledge"][0][0] == pytest.approx(1 - branch_quality(sensor_reliability(meta), ("radar",), "bev"))


def test_what_a_pem_cannot_give_is_refused(setup):
    from study.experiments.compare import compare
    from study.experiments.pem import predict_pem

    run_dir, fit_data, test_data, tmp = setup
    predict_pem(tmp / "seed.json", test_data, tmp / "r")
    with pytest.raises(UserError, match="perception error model.*give --gates knowledge"):
        compare(run_dir, test_data, gates=("knowledge", "deep"), resamples=0, predictions=tmp / "r", progress=False)
    with pytest.raises(UserError, match="--twins"):
        compare(run_dir, test_data, gates=("knowledge",), resamples=0, predictions=tmp / "r", twins=True,
                progress=False)
    with pytest.raises(UserError, match="strength"):
        predict_pem(tmp / "seed.json", test_data, tmp / "s", strength=0)
    (tmp / "bad.json").write_text("{}")
    with pytest.raises(UserError, match="not a hydrabench-pem"):
        predict_pem(tmp / "bad.json", test_data, tmp / "s")
    doc = json.loads((tmp / "seed.json").read_text())
    from study.engine.gate_data import dataset_sha256

    doc["fit_dataset_sha256"] = dataset_sha256(test_data)
    (tmp / "same.json").write_text(json.dumps(doc))
    with pytest.raises(UserError, match="fitted on this dataset"):
        predict_pem(tmp / "same.json", test_data, tmp / "s")


def test_docs_numbers_are_the_results():
    """docs/pem.md's tables and counts are the results files' numbers."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    doc = (root / "docs" / "pem.md").read_text()
    flat = re.sub(r"\s+", " ", doc)
    check = json.loads((root / "results" / "pem_check_2026-12-07.json").read_text())["check"]
    net, mean = check["sets"]["network"]["methods"], check["sets"]["pem_mean"]["methods"]
    assert check["sets"]["pem_mean"]["of"] == ["pem", "pem2", "pem3"]
    for n in net:
        iv, rg = net[n]["ci95"], mean[n]["map_range"]
        row = (f"| {n} | {net[n]['map']:.3f} [{iv[0]:.3f}, {iv[1]:.3f}] | {mean[n]['map']:.3f} [{rg[0]:.3f}, {rg[1]:.3f}] | "
               f"{'in' if mean[n]['in_network_ci95'] else 'out'} |")
        assert row in doc, row
    inside = check["sets"]["pem_mean"]["per_context_inside"]
    assert f"inside the network's interval in {inside['inside']} of {inside['of']}" in flat
    for pair, co in check["sets"]["network"]["co_detection"].items():
        lifts = ", ".join(f"{check['sets'][x]['co_detection'][pair]['lift']:.2f}" for x in ("pem", "pem2", "pem3"))
        row = f"| {pair.replace('|', ' / ')} | {co['lift']:.2f} | {lifts} |"
        assert row in doc, row
    loadings = json.loads((root / "results" / "pem_check_2026-12-07.json").read_text())["loadings"]
    assert ", ".join(f"{b} {v:g}" for b, v in loadings.items()) + "." in flat
    sweeps = json.loads((root / "results" / "pem_sweep_2026-12-07.json").read_text())["sweeps"]
    below = 0
    for seed, sweep in sweeps.items():
        for p in sweep["points"]:
            a, k = p["all_branches_minus_late"], p["knowledge_minus_all_branches"]
            row = (f"| {p['strength']:g} | {seed} | {p['maps']['late']:.3f} | {p['maps']['all_branches']:.3f} | "
                   f"{a['value']:+.3f} [{a['ci95'][0]:+.3f}, {a['ci95'][1]:+.3f}] | "
                   f"{k['value']:+.3f} [{k['ci95'][0]:+.3f}, {k['ci95'][1]:+.3f}] | {p['seconds']} |")
            assert row in doc, row
            assert a["verdict"] == "above" and k["verdict"] != "above"
            below += k["verdict"] == "below"
    assert f"({below} of 12 below)" in doc
    compare = json.loads((root / "results" / "compare_cpu_frontier_demo_2026-12-05.json").read_text())["methods"]
    a, k = compare["all_branches"]["minus_late"], compare["hydrafusion:knowledge"]["minus_all_branches"]
    assert (f"all_branches - late {a['value']:+.3f} [{a['ci95'][0]:+.3f}, {a['ci95'][1]:+.3f}], knowledge - "
            f"all_branches {k['value']:+.3f} [{k['ci95'][0]:+.3f}, {k['ci95'][1]:+.3f}]") in flat


def test_docs_per_severity_table_is_the_results_file():
    """docs/pem.md's per-severity section: the counts and every cell outside the network's interval."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    flat = re.sub(r"\s+", " ", (root / "docs" / "pem.md").read_text())
    check = json.loads((root / "results" / "pem_check_2026-12-08.json").read_text())["check"]
    net, mean = check["sets"]["network"]["methods"], check["sets"]["pem_mean"]
    for group in ("context", "severity"):
        c = mean[f"per_{group}_inside"]
        assert f"{c['inside']} of {c['of']} (method, {group})" in flat, group
    outside = 0
    for n, row in mean["methods"].items():
        for sv, ok in row["in_network_ci95_per_severity"].items():
            if ok is False:
                outside += 1
                iv = net[n]["ci95_per_severity"][sv]
                cell = (f"| {n} | {sv.split()[1]} | {net[n]['map_per_severity'][sv]:.3f} [{iv[0]:.3f}, {iv[1]:.3f}] | "
                        f"{row['map_per_severity'][sv]:.3f} |")
                assert cell in flat, cell
    assert outside == mean["per_severity_inside"]["of"] - mean["per_severity_inside"]["inside"]


def test_check_groups_by_context_and_severity_and_the_network_checked_against_itself_is_inside(setup, tmp_path):
    """`pem check` with the network's own predictions as the "PEM": every mAP, overall, per context and
    per severity, equals the network's and lies inside its interval; the severity groups are the
    frames' severities (every condition pooled)."""
    from sensors.dataset import DatasetReader
    from study.engine.predictions import predict
    from study.experiments.pem import check

    run_dir, _, test_data, _ = setup
    net = predict(run_dir, test_data, tmp_path / "net", progress=False)
    r = check(run_dir, test_data, net.root, {"pem": net.root}, resamples=20)
    reader = DatasetReader(test_data)
    severities = {f"severity {reader.meta(i).get('severity', 0)}" for i in range(len(reader))}
    net_m, same = r["sets"]["network"]["methods"], r["sets"]["pem"]["methods"]
    for n, row in same.items():
        assert set(row["map_per_severity"]) == severities, n
        for group in ("map", "map_per_context", "map_per_severity"):
            assert row[group] == net_m[n][group], (n, group)
        assert row["in_network_ci95"] in (True, None)
        assert all(v in (True, None) for v in row["in_network_ci95_per_severity"].values()), n
    for group in ("context", "severity"):
        c = r["sets"]["pem"][f"per_{group}_inside"]
        assert c["of"] > 0 and c["inside"] == c["of"], group
