"""`hydrabench bench arch` on a tiny network: every variant in every precision, ratios against the base
of the same run, the sizes the overrides imply, and bad input refused."""

import pytest

from sim.errors import UserError
from study.bench.arch import bench_arch, parse_variant
from study.cli import main
from tests.study.test_bench_amp import TINY


def test_variants_are_timed_in_each_precision_against_the_base():
    # three variants, no warm-up step: where bf16 is emulated (AVX2-only CPUs) each bf16 step of this
    # tiny network takes ~2 s; the loop is the same for every variant (dilation's own effect:
    # tests/fusion/nets/test_cost_options.py)
    variants = {"base": (), "narrow": ("width=0.25",), "nhwc": ("channels_last=true",)}
    r = bench_arch("cpu", ("radar",), variants, ("fp32", "bf16"), batch=2, steps=2, warmup=0, threads=1,
                   overrides=TINY)
    assert list(r["variants"]) == list(variants) and r["base"] == "base"
    base = r["variants"]["base"]
    for name, v in r["variants"].items():
        assert v["overrides"] == list(variants[name])
        for p in ("fp32", "bf16"):
            assert len(v["step_s_all"][p]) == 2 and v["step_s"][p] > 0
            # the ratio of the unrounded medians; the stored step times are rounded to 1 ms (+-0.0005 s
            # each, several % of a tiny network's step) and the ratio to 0.01
            b, s = base["step_s"][p], v["step_s"][p]
            lo, hi = (b - 5e-4) / (s + 5e-4) - 0.005, (b + 5e-4) / max(s - 5e-4, 1e-9) + 0.005
            assert lo <= v["speedup_vs_base"][p] <= hi, (name, p, b, s, v["speedup_vs_base"][p])
        assert v["float16_mib"] == pytest.approx(2 * v["parameters_m"] * 1e6 / 2**20, abs=0.1)
    assert base["speedup_vs_base"] == {"fp32": 1.0, "bf16": 1.0}
    # the narrow variant has fewer weights; channels_last the same ones
    assert r["variants"]["narrow"]["parameters_m"] < base["parameters_m"]
    assert r["variants"]["nhwc"]["parameters_m"] == base["parameters_m"]
    # the same initial weights and frames: channels_last computes what the base computes (fp32)
    assert r["variants"]["nhwc"]["loss_after_steps"]["fp32"] == pytest.approx(base["loss_after_steps"]["fp32"], rel=1e-3)


def test_bad_variants_and_precisions_are_refused():
    assert parse_variant("narrow:width=0.5+channels_last=true") == ("narrow", ("width=0.5", "channels_last=true"))
    assert parse_variant("base:") == ("base", ())
    with pytest.raises(UserError, match="expected NAME:KEY=VALUE"):
        parse_variant("width=0.5")
    with pytest.raises(UserError, match="--precisions"):
        bench_arch("cpu", ("radar",), {"base": ()}, ("fp8",), overrides=TINY)
    with pytest.raises(UserError, match="cannot split into 32 groups"):
        bench_arch("cpu", ("radar",), {"base": (), "odd": ("width=0.3",)}, overrides=TINY)


def test_cli_refuses_a_malformed_variant_in_one_line(capsys):
    assert main(["bench", "arch", "--variant", "width=0.5"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1 and "expected NAME:KEY=VALUE" in err
