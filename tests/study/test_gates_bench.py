"""bench inference's gate figures: every deployable gate timed, top-k runs exactly k branches."""

import pytest
import torch

from study.bench.nets import bench_gates
from tests.fusion.nets.conftest import TINY


@pytest.fixture(autouse=True, scope="module")
def _restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_bench_gates_reports_overhead_per_gate_and_topk_latency():
    r = bench_gates("cpu", repeats=1, threads=1, overrides=TINY, ks=(1, 3, 5))
    assert set(r["gate_overhead_ms"]) == {"knowledge", "knowledge_informed", "deep", "attention", "optimal"}
    assert r["gate_overhead_ms"]["optimal"] is None  # needs ground truth
    for g in ("knowledge", "knowledge_informed", "deep", "attention"):
        assert r["gate_overhead_ms"][g] > 0
        assert set(r["topk_latency_ms"][g]) == {"1", "3", "5"} and all(v > 0 for v in r["topk_latency_ms"][g].values())
        for k in (1, 3, 5):
            assert len(r["topk_branches"][g][str(k)]) == k
        share = r["gate_overhead_share_of_top3"][g]
        # the share is stored to 6 decimals: a knowledge gate's ~1.5e-4 share carries its rounding (abs 5e-7)
        assert share == pytest.approx(r["gate_overhead_ms"][g] / r["topk_latency_ms"][g]["3"], rel=1e-3, abs=1e-6)
    # the knowledge gate's pick for the timed context (fog on the motorway, severity 4): radar-bearing first
    assert set(r["topk_branches"]["knowledge"]["1"]) <= {"radar", "radar_lidar"}
    # untrained learned gates predict a constant: ties keep the branch order
    assert r["topk_branches"]["deep"]["3"] == ["radar", "camera_left", "camera_right"]


def test_bench_inference_prints_and_emits_the_gate_figures(monkeypatch, capsys, tmp_path):
    """The command's text and JSON carry bench_gates' figures (the slow parts replaced by stubs)."""
    import json

    import study.bench.boxes
    import study.bench.nets
    from study.cli import main

    gates = bench_gates("cpu", repeats=1, threads=1, overrides=TINY, ks=(1, 3, 5))
    fake = {"latency_ms": {"all_branches": 10.0}, "latency_ms_per_frame_batch_8": {"all_branches": 5.0},
            "peak_rss_mb": {"all_branches": 100.0}, "ratio_top3_to_all": 0.5, "ratio_top3_worst_to_all": 0.6,
            "training_images_per_second": {"radar": 1.0},
            "batch8_gain_per_op_kind": {"all_branches": {"conv": 1.04, "roi_align": 0.82}},
            "op_share_batch_1": {"all_branches": {"conv": 0.625, "roi_align": 0.164}}, **gates}
    calls = []
    monkeypatch.setattr(study.bench.nets, "bench_inference", lambda *a, **k: calls.append(a) or dict(fake))
    monkeypatch.setattr(study.bench.boxes, "bench_box_fusion", lambda **k: {"methods": {}})
    assert main(["bench", "inference"]) == 0
    out = capsys.readouterr().out
    assert calls[-1][3] is None  # no --run: random weights (the option must not collide with the handler)
    assert "gate overhead [ms]: knowledge" in out and "optimal - (needs ground truth)" in out
    assert "top-k with the attention gate [ms]: k=1" in out and "% of top-3" in out
    assert "all_branches: batch-8 gain per operator kind (share of batch-1 time): conv 1.04x (62 %)" in out
    run = tmp_path / "x"
    run.mkdir()
    (run / "config.json").write_text("{}")  # --run is checked to be a training run before any work
    assert main(["bench", "inference", "--json", "--run", str(run)]) == 0
    assert calls[-1][3] == str(run)
    r = json.loads(capsys.readouterr().out)
    assert r["gate_overhead_ms"] == gates["gate_overhead_ms"] and set(r["topk_latency_ms"]["deep"]) == {"1", "3", "5"}
