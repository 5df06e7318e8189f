"""Gate training on a synthetic gate dataset whose losses depend on the features: a trained gate
beats the constant predictor on held-out MAE, and training resumes to identical weights."""

import dataclasses

import numpy as np
import pytest
import torch

from fusion.nets.branch_gates import GATES
from study.engine.gate_training import (
    GateTrainConfig,
    fit_gate,
    fit_objectives,
    mae,
    predict_losses,
    ranking_agreement,
)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Small convs: one thread (two threads on shared, busy cores make them many times slower)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)

SENSORS = ("radar", "lidar")
BRANCHES = {"radar": ("radar",), "lidar": ("lidar",), "radar_lidar": ("radar", "lidar")}


def synthetic(n, seed):
    """Pooled features (n, 128, 8, 16) float16 whose lidar channels carry a fog level z in 0..1 in the
    top rows only; losses: radar flat, lidar 0.5 + 2 z, radar_lidar 0.8 + z, plus noise."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0, 1, n)
    x = rng.normal(0, 1, (n, 128, 8, 16))
    x[:, 64:, :4, :] += 2.0 * z[:, None, None, None]
    noise = rng.normal(0, 0.05, (n, 3))
    y = np.stack([1.0 + 0 * z, 0.5 + 2.0 * z, 0.8 + z], axis=1) + noise
    return x.astype(np.float16), y.astype(np.float32)


def gate_of(name, seed=0):
    torch.manual_seed(seed)
    return GATES.get(name)(branch_sensors=BRANCHES, branch_frames={b: "bev" for b in BRANCHES},
                           sensors=SENSORS, grid=(8, 16))


@pytest.fixture(scope="module")
def data():
    return synthetic(384, 1), synthetic(64, 2), synthetic(128, 3)


# lr 1e-3 keeps the test short; the command trains at the paper's 5e-5 (same code path)
CFG = GateTrainConfig(gate="deep", epochs=12, batch_size=32, lr=1e-3, seed=0, objective="mae")


@pytest.mark.parametrize("name", ["deep", "attention"])
def test_trained_gate_beats_the_constant_predictor_on_held_out_mae(data, name):
    (xf, yf), (xv, yv), (xt, yt) = data
    gate = gate_of(name)
    fitted = fit_gate(gate, xf, yf, xv, yv, dataclasses.replace(CFG, gate=name), progress=False)
    pred = predict_losses(gate, xt)
    constant = mae(np.broadcast_to(yf.mean(axis=0), yt.shape), yt)
    assert constant > 0.2  # the losses really vary
    assert mae(pred, yt) < 0.5 * constant, (mae(pred, yt), constant)
    assert ranking_agreement(pred, yt, 1) > 0.8  # and it ranks the branches by what the features say
    assert 1 <= fitted["best_epoch"] <= CFG.epochs and len(fitted["history"]) == CFG.epochs
    # the untrained gate is exactly the per-branch training median
    fresh = gate_of(name)
    fresh.fit_normalization(torch.from_numpy(xf), torch.from_numpy(yf))
    assert np.allclose(predict_losses(fresh, xt), np.median(yf, axis=0), atol=1e-6)


def test_gate_on_features_without_information_does_not_beat_the_constant(data):
    """The same training on shuffled targets: no feature explains the losses, so held-out MAE must
    stay at the constant predictor's level (the test above can fail)."""
    (xf, yf), (xv, yv), (xt, yt) = data
    rng = np.random.default_rng(0)
    gate = gate_of("deep")
    fit_gate(gate, xf, yf[rng.permutation(len(yf))], xv, yv[rng.permutation(len(yv))], CFG, progress=False)
    constant = mae(np.broadcast_to(yf.mean(axis=0), yt.shape), yt)
    assert mae(predict_losses(gate, xt), yt) > 0.8 * constant


def test_gate_training_resumes_to_identical_weights(data, tmp_path):
    (xf, yf), (xv, yv), _ = data
    cfg = dataclasses.replace(CFG, epochs=4)
    straight = gate_of("attention")
    fit_gate(straight, xf[:128], yf[:128], xv, yv, cfg, progress=False)
    first = gate_of("attention")
    fit_gate(first, xf[:128], yf[:128], xv, yv, dataclasses.replace(cfg, epochs=2), out=tmp_path, progress=False)
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert state["epoch"] == 2 and (tmp_path / "metrics.csv").read_text().count("\n") == 3
    resumed = gate_of("attention", seed=123)  # different init: everything must come from the checkpoint
    fitted = fit_gate(resumed, xf[:128], yf[:128], xv, yv, cfg, out=tmp_path, progress=False, state=state)
    assert len(fitted["history"]) == 4
    for (k, a), (_, b) in zip(straight.state_dict().items(), resumed.state_dict().items()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=k)


def with_difficulty(xy, seed):
    """The same frames with a large per-frame difficulty d ~ U(0, 3) added to every branch's loss
    (what every choice on a hard frame shares): the best branch is unchanged, MAE now mostly measures d."""
    x, y = xy
    d = np.random.default_rng(seed).uniform(0, 3, (len(y), 1)).astype(np.float32)
    return x, y + d


@pytest.mark.parametrize("objective", ["mae", "centred", "soft_ce", "expected"])
def test_each_objective_trains_a_gate_whose_choice_beats_the_constant(data, objective):
    """fusion.gate_objectives through fit_gate with a real gate: lidar is best below z = 0.25, radar
    above, under a shared difficulty the features do not show; the epoch is picked on validation regret."""
    from fusion.gate_objectives import choose, constant_choice, judge

    (xf, yf), (xv, yv), (xt, yt) = (with_difficulty(d, s) for d, s in zip(data, (11, 12, 13)))
    gate = gate_of("deep")
    cfg = dataclasses.replace(CFG, objective=objective)
    fitted = fit_gate(gate, xf, yf, xv, yv, cfg, progress=False)
    j = judge(yt, choose(predict_losses(gate, xt)), constant_choice(yf))
    assert j["constant_regret"] > 0.04, j  # the constant (radar) is wrong on a quarter of the frames (0.054)
    assert j["regret"] < 0.5 * j["constant_regret"], (objective, j)
    assert fitted["best_val_regret"] == min(r["val_regret"] for r in fitted["history"])
    assert fitted["tau"] > 0 and f"train_{objective}" in fitted["history"][0]


def test_gate_config_refuses_an_unknown_objective_and_a_negative_tau():
    from sim.errors import UserError

    with pytest.raises(UserError, match="gate objective 'ce'"):
        GateTrainConfig(objective="ce")
    with pytest.raises(UserError, match="tau"):
        GateTrainConfig(tau=-1.0)
    with pytest.raises(UserError, match="select_on"):
        GateTrainConfig(select_on="test")


def test_auto_objective_keeps_the_lowest_validation_regret_and_never_reads_the_test_frames(data, tmp_path):
    """--objective auto: one gate per objective, the kept one has the lowest validation regret; the
    test frames are not passed in at all (fit_objectives sees fit and validation frames only)."""
    from fusion.gate_objectives import OBJECTIVES, choose, regret

    (xf, yf), (xv, yv), _ = (with_difficulty(d, s) for d, s in zip(data, (11, 12, 13)))
    cfg = dataclasses.replace(CFG, objective="auto", epochs=4)
    settings = {**dataclasses.asdict(cfg), "data_key": "synthetic"}
    gate, fitted, table, kept = fit_objectives(lambda: gate_of("deep"), xf, yf, xv, yv, cfg, tmp_path, settings,
                                               False, "deep gate", progress=False, extra={"data_key": "synthetic"})
    assert list(table) == list(OBJECTIVES.names())
    assert kept == min(table, key=lambda n: table[n]["val_regret"])
    assert fitted["best_val_regret"] == table[kept]["val_regret"]
    assert regret(yv, choose(predict_losses(gate, xv))) == pytest.approx(table[kept]["val_regret"], abs=1e-5)
    assert (tmp_path / "metrics.csv").read_text() == (tmp_path / "objectives" / kept / "metrics.csv").read_text()
    # a second call resumes every objective's checkpoint and keeps the same one
    again = fit_objectives(lambda: gate_of("deep"), xf, yf, xv, yv, cfg, tmp_path, settings, False, "deep gate",
                           progress=False, extra={"data_key": "synthetic"})
    assert again[3] == kept and again[2] == table
    # without validation frames there is nothing to choose on: the papers' MAE, in out/
    _, _, alone, kept0 = fit_objectives(lambda: gate_of("deep"), xf, yf, xv[:0], yv[:0],
                                        dataclasses.replace(cfg, epochs=1), tmp_path / "noval", settings, False,
                                        "deep gate", progress=False)
    assert kept0 == "mae" and list(alone) == ["mae"] and (tmp_path / "noval" / "metrics.csv").exists()


def context_synthetic(n, seed):
    """Features that say nothing (noise) and frames whose best branch is set by their context
    label: radar is best in fog and snow, lidar elsewhere (on city, motorway, rural, junction clear frames)."""
    rng = np.random.default_rng(seed)
    contexts = ["city", "motorway", "fog", "snow", "rural", "junction"]
    ctx = [contexts[i] for i in rng.integers(0, len(contexts), n)]
    metas = [{"context": c} for c in ctx]
    bad_weather = np.array([c in ("fog", "snow") for c in ctx], dtype=float)
    x = rng.normal(0, 1, (n, 128, 8, 16)).astype(np.float16)
    y = np.stack([1.0 - 0.5 * bad_weather, 0.7 + 0.8 * bad_weather, 0.9 + 0.3 * bad_weather], axis=1)
    return x, (y + rng.normal(0, 0.05, y.shape)).astype(np.float32), metas


@pytest.mark.parametrize("pooling", ["global", "grid"])
def test_a_gate_that_reads_the_context_label_learns_what_the_features_do_not_show(pooling):
    """With `context`, the gate also reads the layout one-hot and the conditions multi-hot
    (`with_context`, through its own weights into the MLP's hidden layer); the losses here depend on
    the label alone, so only such a gate beats the constant. The compact (global) gate learns it
    outright (measured regret 0.000 against the constant's 0.199); the grid gate, whose convs hand
    the MLP 128 outputs of pure noise, learns it partly in 12 epochs (0.137)."""
    from fusion.gate_objectives import choose, constant_choice, judge
    from fusion.nets.branch_gates import context_features, with_context

    (xf, yf, mf), (xv, yv, mv), (xt, yt, mt) = (context_synthetic(n, s) for n, s in ((256, 1), (64, 2), (128, 3)))
    cfg = dataclasses.replace(CFG, objective="centred")
    results = {}
    for context in (False, True):
        torch.manual_seed(0)
        gate = GATES.get("deep")(branch_sensors=BRANCHES, branch_frames={b: "bev" for b in BRANCHES}, sensors=SENSORS,
                                 grid=(8, 16), context=context, pooling=pooling)
        add = (lambda x, m: with_context(x, m)) if context else (lambda x, m: x)
        fit_gate(gate, add(xf, mf), yf, add(xv, mv), yv, cfg, progress=False)
        pred = predict_losses(gate, xt, metas=mt)  # the planes are appended here from the metas
        results[context] = judge(yt, choose(pred), constant_choice(yf))
    assert results[True]["constant_regret"] > 0.1, results  # one branch is wrong on a third of the frames
    bound = 0.2 if pooling == "global" else 0.85
    assert results[True]["regret"] < bound * results[True]["constant_regret"], results
    assert results[True]["regret"] < results[False]["regret"], results
    assert results[False]["regret"] > 0.7 * results[False]["constant_regret"], results  # noise: nothing to learn
    assert len(context_features()) == 8 and with_context(xt[:2], mt[:2]).shape == (2, 136, 8, 16)
    planes = with_context(xt[:1], [{"context": "city+night+rain"}])[0, 128:, 3, 5]
    assert sorted(n for n, v in zip(context_features(), planes) if v) == ["city", "night", "rain"]


def test_gate_input_options_are_checked_and_saved_gates_without_them_load():
    from sim.errors import UserError

    with pytest.raises(UserError, match="attention gate attends"):
        GateTrainConfig(gate="attention", pooling="global")
    with pytest.raises(UserError, match="pooling"):
        GateTrainConfig(pooling="max")
    assert "context" not in GateTrainConfig().gate_options()  # as before: old gate.pt options build the same gate
    gate = gate_of("deep")
    assert "context" not in gate.options and not gate.context
    with pytest.raises(ValueError, match="context planes"):
        GATES.get("deep")(branch_sensors=BRANCHES, branch_frames={b: "bev" for b in BRANCHES}, sensors=SENSORS,
                          grid=(8, 16), context=True).predict_prepared(torch.zeros(2, 128, 8, 16))


def context_visible(n, seed):
    """Frames of four contexts whose lidar channels show the context (a level per context in the top
    rows) and whose per-branch losses are the context's profile plus per-frame noise (sd 0.3) larger
    than the profile's differences (0.2-0.4): each frame's own best branch is mostly noise, its
    context's best is not (radar in fog and snow, lidar in city and rural)."""
    rng = np.random.default_rng(seed)
    names = ["city", "fog", "rural", "snow"]
    profile = {"city": (1.0, 0.6, 0.8), "fog": (0.7, 1.1, 0.9), "rural": (1.0, 0.7, 0.9), "snow": (0.8, 1.2, 1.0)}
    ctx = [names[i] for i in rng.integers(0, len(names), n)]
    x = rng.normal(0, 1, (n, 128, 8, 16))
    x[:, 64:, :4, :] += np.array([2.0 * names.index(c) for c in ctx])[:, None, None, None]
    y = np.array([profile[c] for c in ctx]) + rng.normal(0, 0.3, (n, 3))
    return x.astype(np.float16), y.astype(np.float32), ctx


def test_the_context_router_learns_the_context_table_and_is_kept_or_dropped_by_validation_regret(tmp_path):
    """Issue 36 item 7: with the fitting frames' contexts, "auto" trains one more candidate, the
    context classifier ("context": MAE against each frame's context row of the per-context table);
    its choice is the table's for the context the features show, so its test regret is near the
    per-context constant's and far below the best constant's; its targets are the table's rows, not
    the frame's own (noisy) costs; it is judged on the validation frames' own costs like the others,
    and it resumes as a router (its checkpoint is tagged)."""
    from fusion.gate_objectives import (
        OBJECTIVES,
        apply_context_choice,
        choose,
        constant_choice,
        context_choice,
        context_targets,
        regret,
    )
    from study.engine.gate_training import OBJECTIVE_LABEL, ROUTER

    (xf, yf, cf), (xv, yv, cv), (xt, yt, ct) = (context_visible(n, s) for n, s in ((512, 1), (128, 2), (512, 3)))
    cfg = dataclasses.replace(CFG, objective="auto", epochs=6)
    settings = {**dataclasses.asdict(cfg), "data_key": "synthetic"}
    gate, fitted, table, kept = fit_objectives(lambda: gate_of("deep"), xf, yf, xv, yv, cfg, tmp_path, settings,
                                               False, "deep gate", progress=False, contexts_fit=cf,
                                               extra={"data_key": "synthetic"})
    assert list(table) == [*OBJECTIVES.names(), ROUTER] and set(OBJECTIVE_LABEL) >= set(table)
    assert kept == min(table, key=lambda n: table[n]["val_regret"])
    # the router alone, rebuilt from its checkpoint's best state
    state = torch.load(tmp_path / "objectives" / ROUTER / "checkpoint.pt", weights_only=False)
    assert state["router"] == ROUTER and state["config"]["objective"] == "mae"
    router = gate_of("deep")
    router.load_state_dict(state["best_state"])
    by_table = apply_context_choice(context_choice(yf, cf), ct, constant_choice(yf))
    r_router, r_table = regret(yt, choose(predict_losses(router, xt))), regret(yt, by_table)
    r_const = regret(yt, np.full(len(yt), constant_choice(yf)))
    assert r_table < 0.8 * r_const, (r_table, r_const)  # the context is worth knowing here
    assert r_router < r_table + 0.25 * (r_const - r_table), (r_router, r_table, r_const)
    # the targets: the table's rows (the frame's own costs shuffled within its context change nothing)
    rows = context_targets(yf, cf)
    assert rows.shape == yf.shape and np.allclose(rows[np.array(cf) == "fog"], yf[np.array(cf) == "fog"].mean(0))
    shuffled = yf.copy()
    for c in set(cf):
        idx = np.flatnonzero(np.array(cf) == c)
        shuffled[idx] = yf[np.random.default_rng(1).permutation(idx)]
    assert not np.array_equal(shuffled, yf) and np.allclose(context_targets(shuffled, cf), rows, atol=1e-6)
    # resumed as it was: the same table, the same kept objective
    again = fit_objectives(lambda: gate_of("deep"), xf, yf, xv, yv, cfg, tmp_path, settings, False, "deep gate",
                           progress=False, contexts_fit=cf, extra={"data_key": "synthetic"})
    assert again[2] == table and again[3] == kept
    # --objective context: the router alone (it needs the contexts)
    alone = dataclasses.replace(cfg, objective=ROUTER, epochs=1)
    with pytest.raises(ValueError, match="contexts_fit"):
        fit_objectives(lambda: gate_of("deep"), xf, yf, xv, yv, alone, tmp_path / "alone", settings, False, "deep gate",
                       progress=False)
    one = fit_objectives(lambda: gate_of("deep"), xf, yf, xv, yv, alone, tmp_path / "alone", settings, False,
                         "deep gate", progress=False, contexts_fit=cf)
    assert one[3] == ROUTER and list(one[2]) == [ROUTER] and (tmp_path / "alone" / "checkpoint.pt").exists()


@pytest.mark.parametrize("k", [1, 2])
def test_the_epoch_is_chosen_by_the_regret_of_the_top_k_the_gate_runs(data, k):
    """GateTrainConfig.k (issue 50 item 5): the validation regret that picks the epoch is that of the
    gate's top k; the kept weights give exactly the recorded best regret at that k."""
    from fusion.gate_objectives import top_k_regret

    (xf, yf), (xv, yv), _ = data
    gate = gate_of("deep")
    cfg = dataclasses.replace(CFG, epochs=3, k=k)
    fitted = fit_gate(gate, xf[:96], yf[:96], xv, yv, cfg, progress=False)
    p = predict_losses(gate, xv)
    assert fitted["best_val_regret"] == round(top_k_regret(yv, p, k), 6)
    assert [r["val_regret"] for r in fitted["history"]][fitted["best_epoch"] - 1] == fitted["best_val_regret"]
    with pytest.raises(Exception, match="k"):
        dataclasses.replace(CFG, k=0)
