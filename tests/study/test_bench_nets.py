"""bench inference: where a forward's time goes, per operator kind."""

from study.bench.nets import OP_KINDS, _worker, op_kind


def test_operator_kinds():
    assert op_kind("aten::mkldnn_convolution") == "conv" and op_kind("aten::conv2d") == "conv"
    assert op_kind("aten::native_batch_norm") == "norm" and op_kind("aten::group_norm") == "norm"
    assert op_kind("torchvision::roi_align") == "roi_align" and op_kind("torchvision::nms") == "nms"
    assert op_kind("aten::addmm") == "linear" and op_kind("aten::add") == "other"


def test_a_worker_reports_its_time_per_operator_kind():
    r = _worker(("cpu", "paper", ["camera_right"], 1, 1, 2, None, "cpu", False))
    ops = {k: r[f"ops_ms_per_frame/{k}"] for k in OP_KINDS}
    assert ops["conv"] > 0 and ops["roi_align"] > 0 and ops["linear"] > 0
    # the profiled forward's self times add up to about one forward (plus profiler overhead)
    assert 0.3 * r["latency_ms_min"] < sum(ops.values()) < 5 * r["latency_ms"]
