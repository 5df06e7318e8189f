"""`hydrabench theory`: the CLI contract (one JSON object, exact keys, exit 2 on bad input) and its cache."""

import json

import pytest

import study.cli as cli
from study.experiments import theory

RESULT_KEYS = {"mse_single", "mse_full_nominal", "mse_full_true", "mse_selective", "mse_gated", "nees_mean",
               "nees_bounds"}


@pytest.fixture
def hydrabench(monkeypatch):
    """study.cli.main with the theory command registered (as study/cli.py's COMMANDS table will)."""
    monkeypatch.setitem(cli.COMMANDS, "theory", ("study.commands.theory:add_parser", "fusion theory, measured"))

    def run(argv, capsys):
        code = cli.main(argv)
        out, err = capsys.readouterr()
        return code, out, err

    return run


@pytest.fixture
def cache(cache_lock):
    """One cache for every theory test of the session (and the notebook test), held while a test
    uses it so that another xdist worker does not measure the same cells beside it."""
    with cache_lock("theory") as path:
        yield path


def test_help_explains_the_sample_size(hydrabench, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["theory", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for needle in ("--conditions", "--severities", "--frames", "--cache", "mse_full_nominal", "Sample size"):
        assert needle in out


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--conditions", "volcano"], "unknown condition 'volcano'"),
        (["--conditions", "city"], "names no weather condition"),
        (["--conditions", "city+rural+fog"], "names two road layouts"),
        (["--conditions", "fog+fog"], "repeats a condition"),
        (["--severities", "9"], "must be <= 5, got 9"),
        (["--sequences", "1"], "sequences must be >= 2"),
        (["--frames", "3", "--sequences", "4"], "frames (3) must be >= sequences (4)"),
        (["--layout", "moon"], "invalid choice"),
        (["--profile", "gpu"], "unknown profile 'gpu'"),
        (["--cache", "/proc/forbidden/cache"], "/proc is not writable"),
    ],
)
def test_bad_input_exits_2_with_one_line(hydrabench, capsys, argv, needle):
    code, out, err = hydrabench(["theory", *argv], capsys)
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], err


def test_json_has_the_seven_keys_per_condition_and_severity_and_the_cache_makes_reruns_identical(
        hydrabench, capsys, cache):
    # the first two sequences of SMALL_CONFIG's cells (same seeds and frames per sequence): cached
    # by the measured tests or the notebook when they ran first
    argv = ["theory", "--conditions", "fog", "--severities", "0", "5", "--frames", "24", "--sequences", "2",
            "--workers", "1", "--cache", str(cache), "--json"]
    code, out, err = hydrabench(argv, capsys)
    assert code == 0 and out.count("\n") == 1
    first = json.loads(out)
    assert set(first["results"]) == {"fog"} and set(first["results"]["fog"]) == {"0", "5"}
    for sev, cell in first["results"]["fog"].items():
        assert set(cell) == RESULT_KEYS, sev
        assert set(cell["mse_single"]) == {"camera", "lidar", "radar"}
        lo, hi = cell["nees_bounds"]
        assert lo < 2.0 < hi  # the 95 % interval of a mean of chi2(2) values
        assert first["details"]["fog"][sev]["compared"] >= 6
    assert first["details"]["fog"]["5"]["weather"] == "visibility 30-75 m"
    code, out, _ = hydrabench(argv, capsys)
    second = json.loads(out)
    assert second["frames"]["measured"] == 0 and second["frames"]["cached"] == 48
    assert second["results"] == first["results"]
    code, text, _ = hydrabench(argv[:-1], capsys)
    assert code == 0 and "fog (layout motorway)" in text and "full_nom" in text and "visibility 30-75 m" in text


def test_a_stale_cache_entry_is_measured_again(tmp_path):
    spec = theory.sequence_specs(theory.TheoryConfig(frames=2, sequences=2), "fog", 0)[0]
    key = theory.cache_key(spec, 0)
    path = theory.cache_path(tmp_path, key)
    path.write_bytes(b"not an npz archive")
    assert theory.load_cached(path, key) is None
    other = dict(key, extractor_version=key["extractor_version"] - 1)
    assert theory.cache_path(tmp_path, other) != path  # another extractor version, another file


def test_cells_share_seeds_and_severity_zero_is_the_layout():
    cfg = theory.TheoryConfig(conditions=("fog", "rain+night"), frames=10, sequences=3)
    assert theory.sequence_frames(cfg) == [4, 3, 3]
    fog5 = theory.sequence_specs(cfg, "fog", 5)
    rain0 = theory.sequence_specs(cfg, "rain+night", 0)
    assert [s.seed for s in fog5] == [s.seed for s in rain0] == theory.sequence_seeds(cfg)
    assert rain0[0].context == "motorway" and fog5[0].context == "fog"
    assert theory.sequence_specs(cfg, "rain+night", 2)[0].context == "motorway+rain+night"
    assert theory.weather_text("rain+night", 2) == "rain 2.5-5 mm/h, illuminance 10-50 lx"
    assert theory.condition_name("Night+City") == "city+night"
    city = theory.sequence_specs(cfg, "city+night", 0) + theory.sequence_specs(cfg, "city+night", 4)
    assert [s.context for s in city[::3]] == ["city", "night"]  # night's own layout is the city


def test_json_and_text_carry_robust_figures_and_gross_errors_with_causes(hydrabench, capsys, cache):
    from fusion.estimation.error_model import STRATEGIES
    from fusion.estimation.gross import CAUSES, GATE_OUTCOMES, GROSS_BOUND

    argv = ["theory", "--conditions", "fog", "--severities", "5", "--frames", "24", "--sequences", "2",
            "--workers", "1", "--cache", str(cache)]
    code, out, _ = hydrabench([*argv, "--json"], capsys)
    assert code == 0
    det = json.loads(out)["details"]["fog"]["5"]
    for name in ("camera", "lidar", "radar", *STRATEGIES):
        rob = det["robust"][name]
        assert set(rob) == {"n", "mean", "se", "median", "trimmed"}, name
    assert det["robust"]["full_nominal"]["mean"] == json.loads(out)["results"]["fog"]["5"]["mse_full_nominal"]
    paired = det["paired_vs_best_single"]
    assert paired["best_single"] == "radar"  # in dense fog
    assert paired["full_nominal"]["mean"] > 5 * paired["full_nominal"]["se"]  # the fog returns, object by object (8.6 se)
    g = det["gross"]
    assert g["bound"] == pytest.approx(GROSS_BOUND, abs=1e-3)
    for kind in ("nominal", "measured"):
        for s, d in g["per_sensor"][kind].items():
            assert sum(d["causes"].values()) == d["gross"] <= d["n"], (kind, s)
            assert set(d["causes"]) <= set(CAUSES)
            for gate in ("nominal", "measured"):
                assert sum(d["gate"][gate].values()) == d["gross"] and set(d["gate"][gate]) <= set(GATE_OUTCOMES)
    assert g["records"] and all(r["cause"] in CAUSES and r["gross"] for r in g["records"])
    code, text, _ = hydrabench(argv, capsys)
    assert "median" in text and "trimmed" in text and "gross errors" in text and "gated_true" in text
