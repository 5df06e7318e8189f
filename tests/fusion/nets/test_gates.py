"""Gates: top-k invariants, wiring (only selected branches run), the knowledge table, every registry
entry, self-attention, and bad input naming the field."""

import pytest
import torch

from fusion.nets.branch_gates import (
    GATES,
    KNOWLEDGE_TABLE,
    KnowledgeGate,
    SelfAttention2d,
    build_gate,
    check_k,
    pool_features,
    rank_branches,
    sensor_reliability,
    top_k,
)
from sim.errors import UserError
from sim.scenario import CONTEXT_NAMES
from tests.fusion.nets.conftest import make_inputs

BRANCHES = ("radar", "camera_left", "camera_right", "lidar", "camera_both", "camera_lidar", "radar_lidar")
RADAR_BEARING = {"radar", "radar_lidar"}
CAMERA_BRANCHES = {"camera_left", "camera_right", "camera_both", "camera_lidar"}


def _wired(model, gate):
    return type(model)(model.stems, model.branches, gate, None, transform=model.transform).eval()


class _Calls:
    """Counts the samples each branch's forward receives."""

    def __init__(self, model):
        self.samples = {n: 0 for n in model.branches}
        self.hooks = [b.register_forward_hook(self._hook) for b in model.branches.values()]

    def _hook(self, module, args, _out):
        self.samples[module.name] += int(args[0][0].shape[0])

    def remove(self):
        for h in self.hooks:
            h.remove()


# ----- top-k ------------------------------------------------------------------------------------


def test_top_k_invariants_on_random_predictions_with_ties():
    g = torch.Generator().manual_seed(3)
    pred = torch.randint(0, 4, (64, len(BRANCHES)), generator=g).float()  # many ties
    previous = None
    for k in range(1, len(BRANCHES) + 1):
        sel = top_k(pred, BRANCHES, k)
        assert len(sel) == 64
        for i, chosen in enumerate(sel):
            assert len(chosen) == k and len(set(chosen)) == k
            assert list(chosen) == [b for b in BRANCHES if b in chosen]  # branch order
            kept = [pred[i, BRANCHES.index(b)] for b in chosen]
            dropped = [pred[i, j] for j, b in enumerate(BRANCHES) if b not in chosen]
            assert not dropped or max(kept) <= min(dropped)  # the k lowest predicted losses
            for j, b in enumerate(BRANCHES):  # ties resolved towards the earlier branch
                if b in chosen:
                    assert all(BRANCHES[m] in chosen for m in range(j) if pred[i, m] == pred[i, j])
        if previous is not None:
            assert all(set(a) < set(b) for a, b in zip(previous, sel))  # nested: top-k inside top-(k+1)
        previous = sel
    assert top_k(pred, BRANCHES, "all") == [BRANCHES] * 64 == top_k(pred, BRANCHES, None)
    assert rank_branches(torch.tensor([[2.0, 1.0, 1.0, 0.0]])).tolist() == [[3, 1, 2, 0]]


@pytest.mark.parametrize("k", [0, 8, -1, "3", 2.5, True])
def test_bad_k_is_a_value_error_naming_k(k):
    with pytest.raises(ValueError, match="k"):
        check_k(k, len(BRANCHES))
    with pytest.raises(ValueError, match="k"):
        top_k(torch.zeros(2, len(BRANCHES)), BRANCHES, k)


def test_top_k_refuses_wrong_shapes_and_nan():
    with pytest.raises(ValueError, match=r"predicted: expected shape \(B, 7\)"):
        top_k(torch.zeros(2, 6), BRANCHES, 3)
    with pytest.raises(ValueError, match="finite"):
        top_k(torch.tensor([[float("nan")] * 7]), BRANCHES, 3)


# ----- knowledge gate ---------------------------------------------------------------------------


def _knowledge(model, k=None, name="knowledge_informed"):
    """The knowledge gate that reads each frame's severity and lens coverage (the context-only one,
    `knowledge`, is tested against it below)."""
    return build_gate(name, model, k=k)


@pytest.mark.parametrize("context, severities", [("fog", range(1, 6)), ("snow", range(3, 6)),
                                                 ("motorway+snow", range(3, 6)), ("junction+fog", range(4, 6))])
def test_knowledge_gate_prefers_radar_bearing_branches_in_fog_and_snow(model, context, severities):
    gate = _knowledge(model, k=2)
    meta = [{"context": context, "severity": s} for s in severities]
    for chosen in gate(None, meta):
        assert set(chosen) == RADAR_BEARING, (context, chosen)
    # and the cameras get worse with every severity step
    q = [gate.explain({"context": context, "severity": s})["sensor_reliability"]["camera_right"] for s in range(6)]
    assert all(a > b for a, b in zip(q, q[1:]))


@pytest.mark.parametrize("layout", ["city", "junction", "rural"])
def test_knowledge_gate_prefers_camera_branches_in_clear_daylight(model, layout):
    gate = _knowledge(model, k=3)
    (chosen,) = gate(None, [{"layout": layout, "conditions": [], "severity": 0}])
    assert set(chosen) <= CAMERA_BRANCHES, chosen


def test_knowledge_gate_handles_combined_contexts_severities_and_lens_cover(model):
    gate = _knowledge(model)
    every = list(CONTEXT_NAMES) + ["city+night+rain", "motorway+fog+snow", "rural+rain+fog+snow+night"]
    meta = [{"context": c, "severity": s} for c in every for s in (0, 3, 5)]
    pred = gate.predict(None, meta)
    assert pred.shape == (len(meta), len(BRANCHES)) and torch.isfinite(pred).all()
    # the same frame given as FrameDataset's meta (layout + conditions) or as a context name
    a = gate.predict(None, [{"context": "city+night+rain", "severity": 4}])
    b = gate.predict(None, [{"layout": "city", "conditions": ["rain", "night"], "severity": 4}])
    assert torch.equal(a, b)
    # each condition adds its factor: city+night+rain is worse for the camera than either alone
    cam = {c: sensor_reliability({"context": c, "severity": 4}, informed=True)["camera_right"]
           for c in ("city", "city+night", "city+rain", "city+night+rain")}
    assert cam["city+night+rain"] < min(cam["city+night"], cam["city+rain"]) < cam["city"]
    assert cam["city+night+rain"] == pytest.approx(cam["city+night"] * cam["city+rain"] / cam["city"])
    # night is no business of the active sensors
    assert sensor_reliability({"context": "city+night", "severity": 5}, informed=True)["lidar"] == sensor_reliability(
        {"context": "city", "severity": 0}, informed=True)["lidar"]
    # drops on the right lens move the right camera down the ranking, not the left one
    clear = {"context": "city", "severity": 0}
    covered = {**clear, "weather": {"lens_coverage_pct": [0.0, 60.0]}}
    q0, q1 = gate.explain(clear)["branch_quality"], gate.explain(covered)["branch_quality"]
    assert q1["camera_right"] < q0["camera_right"] - 0.5 and q1["camera_left"] == q0["camera_left"]
    assert gate.explain(covered)["ranking"].index("camera_left") < gate.explain(covered)["ranking"].index("camera_right")


def test_knowledge_table_has_a_reason_for_every_context_factor():
    assert set(KNOWLEDGE_TABLE) == set(CONTEXT_NAMES)
    for name, row in KNOWLEDGE_TABLE.items():
        assert len(row.reason) > 40, name
        assert all(0.0 < getattr(row, m) <= 1.0 for m in ("camera", "lidar", "radar")), name
    # HydraFusion Table 1: radar good in rain, fog, snow and night; camera poor in all four
    for c in ("rain", "fog", "snow", "night"):
        assert KNOWLEDGE_TABLE[c].radar >= 0.85 and KNOWLEDGE_TABLE[c].camera <= 0.4, c
    assert KNOWLEDGE_TABLE["city"].camera > KNOWLEDGE_TABLE["city"].lidar > KNOWLEDGE_TABLE["city"].radar


@pytest.mark.parametrize("meta, field", [
    (None, "meta"),
    ([{"severity": 2}], r"meta\[0\]: the knowledge gate needs the frame's context"),
    ([{"layout": "moon", "conditions": [], "severity": 0}], r"meta\[0\]\['layout'\]"),
    ([{"layout": "city", "conditions": ["hail"], "severity": 2}], r"meta\[0\]\['conditions'\]"),
    ([{"context": "fog", "severity": 9}], r"meta\[0\]\['severity'\]"),
    ([{"context": "fog"}], r"meta\[0\]\['severity'\]"),
    (["fog"], r"meta\[0\]: expected a dict"),
])
def test_knowledge_gate_bad_meta_names_the_field(model, meta, field):
    with pytest.raises(ValueError, match=field):
        _knowledge(model, k=1)(None, meta)


# ----- every registry entry ---------------------------------------------------------------------


def _meta(model, batch):
    losses = [{b: float((i * 5 + j * 3) % 7) for j, b in enumerate(model.branches)} for i in range(batch)]
    contexts = ["fog", "city", "snow", "city+night+rain"]
    return [{"context": contexts[i % 4], "severity": 4 if i % 2 == 0 else 0, "branch_losses": losses[i]}
            for i in range(batch)]


@pytest.mark.parametrize("name", GATES.names())
def test_every_gate_predicts_one_loss_per_branch_and_runs_wired_into_the_model(model, name):
    torch.manual_seed(0)
    gate = build_gate(name, model, k=2)
    if gate.trainable:  # move the last layer off zero so the ranking depends on the features
        torch.nn.init.normal_(gate.mlp[-1].weight, std=0.5)
    inputs = make_inputs(model, 3, seed=5)
    meta = _meta(model, 3)
    with torch.no_grad():
        features = model.extract_features(inputs)
        pred = gate.predict(features, meta)
        chosen = gate(features, meta)
        assert pred.shape == (3, len(model.branches)) and pred.dtype == torch.float32 and torch.isfinite(pred).all()
        assert chosen == top_k(pred, list(model.branches), 2)
        wired = _wired(model, gate)
        calls = _Calls(wired)
        try:
            out = wired(inputs, meta=meta)
        finally:
            calls.remove()
    assert [tuple(o) for o in out] == chosen
    assert sum(calls.samples.values()) == 3 * 2  # k branch runs per sample, no more
    for b, n in calls.samples.items():
        assert n == sum(b in c for c in chosen), b
    if name == "optimal":  # the two lowest a-posteriori losses
        for m, c in zip(meta, chosen):
            assert set(c) == set(sorted(m["branch_losses"], key=lambda b: (m["branch_losses"][b],
                                                                              list(model.branches).index(b)))[:2])


def test_wired_gate_runs_only_selected_branches_and_matches_running_all(model):
    gate = _knowledge(model, k=2)
    inputs = make_inputs(model, 2, seed=1)
    meta = [{"context": "fog", "severity": 5}, {"layout": "city", "conditions": [], "severity": 0}]
    wired = _wired(model, gate)
    calls = _Calls(wired)
    try:
        with torch.no_grad():
            out = wired(inputs, meta=meta)
    finally:
        calls.remove()
    assert [set(o) for o in out] == [RADAR_BEARING, {"camera_both", "camera_lidar"}]
    assert calls.samples == {"radar": 1, "radar_lidar": 1, "camera_both": 1, "camera_lidar": 1,
                             "camera_left": 0, "camera_right": 0, "lidar": 0}
    with torch.no_grad():  # a branch's detections do not depend on which others run
        everything = model(inputs, selection=list(model.branches))
    for i, o in enumerate(out):
        for name, d in o.items():
            for key in ("boxes", "scores", "labels"):
                assert torch.allclose(d[key].float(), everything[i][name][key].float(), atol=1e-5), (i, name, key)
    # changing k on the gate changes how many branches run
    gate.k = 1
    with torch.no_grad():
        assert [len(o) for o in wired(inputs, meta=meta)] == [1, 1]


def test_unknown_gate_and_bad_options_raise(model):
    with pytest.raises(UserError, match="unknown gate 'magic'"):
        build_gate("magic", model)
    with pytest.raises(ValueError, match="k: must be in 1..7"):
        build_gate("deep", model, k=9)
    with pytest.raises(ValueError, match="grid"):
        build_gate("deep", model, grid=(2, 16))
    with pytest.raises(ValueError, match="sensors"):
        build_gate("attention", model, sensors=["sonar"])
    with pytest.raises(ValueError, match=r"meta\[1\]\['branch_losses'\]: the optimal gate .* needs ground truth"):
        build_gate("optimal", model, k=1)(None, [{"branch_losses": {b: 0.0 for b in model.branches}}, {}])
    with pytest.raises(ValueError, match=r"meta\[0\]\['branch_losses'\]: no loss for branch 'radar'"):
        build_gate("optimal", model, k=1)(None, [{"branch_losses": {"lidar": 1.0}}])


# ----- learned-gate parts -----------------------------------------------------------------------


def test_pool_features_brings_every_sensor_to_one_grid(model):
    with torch.no_grad():
        f = model.extract_features(make_inputs(model, 2))
    sensors = ["camera_left", "radar"]
    x = pool_features(f, sensors, (4, 8))
    assert x.shape == (2, 128, 4, 8)
    # stem maps of 16 x 24 (camera) and 16 x 16 (BEV) cells pool exactly: every map keeps its mean
    assert f["camera_left"].shape[2:] == (16, 24) and f["radar"].shape[2:] == (16, 16)
    assert torch.allclose(x[:, :64].mean(dim=(2, 3)), f["camera_left"].mean(dim=(2, 3)), atol=1e-5)
    assert torch.allclose(x[:, 64:].mean(dim=(2, 3)), f["radar"].mean(dim=(2, 3)), atol=1e-5)
    assert torch.allclose(x[:, 64:, 0, 0], f["radar"][:, :, :4, :2].mean(dim=(2, 3)), atol=1e-5)
    with pytest.raises(ValueError, match="no stem features for sensor 'lidar'"):
        pool_features({"radar": f["radar"]}, ["lidar"], (4, 8))
    with pytest.raises(ValueError, match=r"features\['radar'\]: expected a \(B, 64, h, w\)"):
        pool_features({"radar": f["radar"][:, :3]}, ["radar"], (4, 8))


def test_self_attention_starts_as_identity_and_attends_with_rows_summing_to_one():
    torch.manual_seed(0)
    layer = SelfAttention2d(16)
    x = torch.randn(2, 16, 4, 8)
    assert torch.equal(layer(x), x)  # gamma = 0
    with torch.no_grad():
        layer.gamma.fill_(1.0)
    y = layer(x)
    beta = layer.last_attention
    assert beta.shape == (2, 32, 32) and torch.allclose(beta.sum(-1), torch.ones(2, 32), atol=1e-5)
    # y_j = x_j + sum_i beta[j, i] h_i, written out for one position
    h = layer.h(x).flatten(2)
    j = 5
    expected = x.flatten(2)[:, :, j] + (beta[:, j, :].unsqueeze(1) * h).sum(-1)
    assert torch.allclose(y.flatten(2)[:, :, j], expected, atol=1e-5)


def test_untrained_conv_gates_predict_the_constant_centre(model):
    for name in ("deep", "attention"):
        gate = build_gate(name, model)
        with torch.no_grad():
            gate.target_center.copy_(torch.arange(len(model.branches), dtype=torch.float32))
            pred = gate.predict(model.extract_features(make_inputs(model, 2)))
        assert torch.equal(pred, gate.target_center.expand(2, -1)), name
        assert (gate.attn is not None) == (name == "attention")
    x = torch.zeros(2, 10, 8, 16)
    with pytest.raises(ValueError, match=r"x: expected pooled features \(B, 320, 8, 16\)"):
        build_gate("deep", model).predict_prepared(x)


def test_the_default_knowledge_gate_reads_the_context_label_only(model):
    """HydraFusion's knowledge gate knows the context, not the frame's severity or the drops on a lens:
    its ranking is the informed gate's at CONTEXT_SEVERITY without lens cover, whatever the frame says."""
    from fusion.nets.branch_gates import CONTEXT_SEVERITY

    plain, informed = _knowledge(model, name="knowledge"), _knowledge(model)
    frames = [{"context": "city+rain", "severity": s, "weather": {"lens_coverage_pct": [0.0, c]}}
              for s in (1, 3, 5) for c in (0.0, 60.0)]
    pred = plain.predict(None, frames)
    assert all(torch.equal(pred[0], row) for row in pred)  # severity and lens cover change nothing
    assert torch.equal(pred[0], informed.predict(None, [{"context": "city+rain", "severity": CONTEXT_SEVERITY}])[0])
    assert not torch.equal(informed.predict(None, frames[:1]), informed.predict(None, frames[-1:]))
    # a label without a severity is enough for it, not for the informed gate
    assert torch.equal(plain.predict(None, [{"context": "city+rain"}]), pred[:1])
    with pytest.raises(ValueError, match="severity"):
        informed.predict(None, [{"context": "city+rain"}])
    assert plain.explain({"context": "fog"})["severity"] == CONTEXT_SEVERITY


def test_registry_names_are_the_five_gates():
    assert set(GATES.names()) == {"knowledge", "knowledge_informed", "deep", "attention", "optimal"}
    assert GATES.get("knowledge") is KnowledgeGate and GATES.get("optimal").reads == "losses"
    assert {n for n in GATES.names() if GATES.get(n).trainable} == {"deep", "attention"}
