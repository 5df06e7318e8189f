"""`hydrabench bench amp` on a tiny network: both precisions train from the same weights on the same
frames, the report says what --amp auto picks on this CPU and why."""

import statistics

import pytest

from sim.errors import UserError
from study.bench.amp import bench_amp
from study.engine.device import native_bf16

TINY = {"camera": {"size": (64, 96)}, "bev": {"size": (64, 64)}, "roi_channels": 32, "box_head_width": 64,
        "box_batch_size_per_image": 32, "rpn_pre_nms_top_n_train": 200, "rpn_post_nms_top_n_train": 100}


def test_bench_amp_measures_both_precisions_from_the_same_start():
    r = bench_amp("cpu", ("radar",), batch=2, steps=2, warmup=1, threads=1, overrides=TINY)
    assert r["branches"] == ["radar"] and r["threads"] == 1
    assert all(len(r["step_s_all"][p]) == 2 and min(r["step_s_all"][p]) > 0 for p in ("fp32", "bf16"))
    # the stored speedup is the ratio of the medians of the stored step times, kept to 3 significant
    # figures (times to 4), whatever its size: 0.064 where bf16 is emulated, about 2 with AMX
    median = {p: statistics.median(r["step_s_all"][p]) for p in ("fp32", "bf16")}
    assert r["speedup_bf16"] == pytest.approx(median["fp32"] / median["bf16"], rel=6e-3)
    assert r["speedup_bf16"] == float(f"{r['speedup_bf16']:.3g}")
    fp32, bf16 = r["loss_per_step"]["fp32"], r["loss_per_step"]["bf16"]
    assert len(fp32) == len(bf16) == 3
    # the same weights, frames and sampling: the first losses differ by bf16 rounding of the backbone only
    assert fp32[0] != bf16[0] and abs(fp32[0] - bf16[0]) < 0.05 * fp32[0]
    assert (r["native_bf16"], r["native_bf16_reason"]) == native_bf16("cpu")
    assert r["amp_auto_picks"] == ("bf16" if r["native_bf16"] else "fp32")


def test_bench_amp_refuses_unknown_branches():
    with pytest.raises(UserError, match="unknown branch 'sonar'"):
        bench_amp("cpu", ("sonar",), overrides=TINY)


@pytest.fixture(scope="module")
def parity_data(shared_dataset):
    from sensors.generate import GenerateConfig

    # 3 one-frame sequences per context: 2 train, 1 test each (the test split has 2 sequences)
    return shared_dataset(GenerateConfig(contexts=("fog", "motorway"), frames_per_context=3, sequence_length=1, seed=4,
                                         twins=False))


# the parity run's mechanics (same start, both precisions trained, scored and resumed) do not depend on
# the network's width: a quarter-width radar branch with a small head costs a fifth of the full one in
# fp32 and far less where bf16 is emulated (an AVX2-only CPU runs bf16 autocast ~16x slower than fp32)
NARROW = ["--model", "width=0.25", "--model", "roi_channels=32", "--model", "box_head_width=64"]


def test_amp_parity_trains_both_precisions_and_scores_them_on_the_same_test_frames(parity_data, tmp_path, capsys):
    import json

    from study.cli import main

    argv = ["bench", "amp-parity", str(parity_data), "--out", str(tmp_path / "par"), "--epochs", "1",
            "--warmup-steps", "1", "--bootstrap", "20", "--threads", "1", "--json", *NARROW]
    assert main(argv) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["branches"] == ["radar"] and r["test_frames"] == 2
    assert {p: r["runs"][p]["compute"]["precision"] for p in ("fp32", "bf16")} == {"fp32": "fp32", "bf16": "bf16"}
    for p in ("fp32", "bf16"):
        run = r["runs"][p]
        assert len(run["loss_total_per_epoch"]) == 1 and run["train_seconds"] > 0
        assert set(run["branches"]["radar"]) == {"map", "map_vehicles"}
    iv = r["ci95_vehicle_map"]["radar"]
    assert r["ci95_vehicle_map"]["sequences"] == 2 and len(iv["bf16_minus_fp32"]) == 2
    assert iv["bf16_minus_fp32"][0] <= iv["bf16_minus_fp32"][1]
    # the two runs are resumed, not trained again: the same numbers, no new epoch
    assert main(argv) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["runs"]["fp32"]["loss_total_per_epoch"] == r["runs"]["fp32"]["loss_total_per_epoch"]
    assert again["runs"]["bf16"]["branches"] == r["runs"]["bf16"]["branches"]
    # the overrides reach both runs (their config.json records the resolved profile)
    for p in ("fp32", "bf16"):
        fields = json.loads((tmp_path / "par" / p / "config.json").read_text())["profile_fields"]
        assert (fields["width"], fields["roi_channels"], fields["box_head_width"]) == (0.25, 32, 64)
    assert json.loads((tmp_path / "par" / "amp_parity.json").read_text())["runs"] == again["runs"]


def test_amp_parity_refuses_a_folder_of_other_files(parity_data, tmp_path, capsys):
    from study.cli import main

    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    assert main(["bench", "amp-parity", str(parity_data), "--out", str(tmp_path / "mine")]) == 2
    err = capsys.readouterr().err
    assert "holds other files than amp-parity's" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["notes.txt"]
