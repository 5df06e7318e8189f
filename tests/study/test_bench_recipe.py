"""`hydrabench bench recipe` on a tiny dataset: candidates trained alike, scored per epoch on the runs'
gate split (never test frames), curves in core-hours, the choice at equal budget, resume, refusals."""

import json

import pytest
import torch

from sensors.generate import GenerateConfig
from sim.errors import UserError
from study.bench.recipe import _curve_at, aim_reached, bench_recipe, parse_candidate
from study.cli import main
from study.engine.scoring import frames_for


@pytest.fixture(autouse=True, scope="module")
def _restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def data(shared_dataset):
    return shared_dataset(GenerateConfig(contexts=("city", "fog"), frames_per_context=8, sequence_length=2, seed=6))


CANDIDATES = {"base": {"model": ("width=0.25",)}, "fast": {"lr": 0.04, "model": ("width=0.25",)}}


def test_candidates_are_scored_per_epoch_on_the_gate_split_and_chosen_at_equal_budget(data, tmp_path, monkeypatch):
    out = tmp_path / "recipe"
    r = bench_recipe(str(data), out, "radar", CANDIDATES, epochs=2, threads=1, bootstrap=10, progress=False)
    assert list(r["candidates"]) == ["base", "fast"] and r["held_out"]["split"] == "gate"
    run_cfg = json.loads((out / "base" / "config.json").read_text())
    held, _ = frames_for(run_cfg, str(data), "gate")
    test, _ = frames_for(run_cfg, str(data), "test")
    train_, _ = frames_for(run_cfg, str(data), "train")
    assert r["held_out"]["frames"] == len(held) > 0 and not set(held) & (set(test) | set(train_))
    assert run_cfg["lr"] == 0.02 and json.loads((out / "fast" / "config.json").read_text())["lr"] == 0.04
    for c in r["candidates"].values():
        xs = [p["core_hours"] for p in c["curve"]]
        assert [p["epoch"] for p in c["curve"]] == [1, 2] and xs[0] < xs[1]
        assert xs[-1] == pytest.approx(c["train_seconds"] / 3600.0, abs=1e-3)  # one thread
        ys = [p["map_vehicles"] or 0.0 for p in c["curve"]]
        assert c["map_vehicles_at_budget"] == pytest.approx(_curve_at(xs, ys, r["budget_core_hours"]), abs=1e-4)
        assert len(c["ci95_map_vehicles_last_epoch"]) == 2
    assert r["budget_core_hours"] == min(c["curve"][-1]["core_hours"] for c in r["candidates"].values())
    best = max(c["map_vehicles_at_budget"] for c in r["candidates"].values())
    assert r["candidates"][r["chosen"]]["map_vehicles_at_budget"] == best
    assert json.loads((out / "recipe.json").read_text())["chosen"] == r["chosen"]
    # a second call resumes: nothing is trained again, the same curves come back
    again = bench_recipe(str(data), out, "radar", CANDIDATES, epochs=2, threads=1, bootstrap=10, progress=False)
    assert [c["curve"] for c in again["candidates"].values()] == [c["curve"] for c in r["candidates"].values()]
    from study.bench.recipe import plot_recipe

    plot_recipe(again, out / "curves.png")  # its own figure beside the runs does not stop a resume
    assert (out / "curves.png").stat().st_size > 0
    import study.engine.scoring

    def no_loading(*a, **k):
        raise AssertionError("a kept score was computed again")

    monkeypatch.setattr(study.engine.scoring, "load_run", no_loading)  # scores kept beside each run: nothing rescored
    kept = bench_recipe(str(data), out, "radar", CANDIDATES, epochs=2, threads=1, bootstrap=0, progress=False)
    assert [c["curve"] for c in kept["candidates"].values()] == [c["curve"] for c in r["candidates"].values()]
    monkeypatch.undo()
    memo = json.loads((out / "base" / "held_out_scores.json").read_text())
    memo["epochs"]["1"]["sha256"] = "0" * 64  # another checkpoint under that name: scored again, same value
    (out / "base" / "held_out_scores.json").write_text(json.dumps(memo))
    again = bench_recipe(str(data), out, "radar", CANDIDATES, epochs=2, threads=1, bootstrap=0, progress=False)
    assert again["candidates"]["base"]["curve"] == r["candidates"]["base"]["curve"]
    (out / "notes.txt").write_text("mine")
    with pytest.raises(UserError, match="holds other files"):
        bench_recipe(str(data), out, "radar", CANDIDATES, epochs=2, threads=1, progress=False)


def test_curve_interpolation_and_candidate_parsing():
    assert _curve_at([1.0, 2.0], [0.2, 0.4], 1.5) == pytest.approx(0.3)
    assert _curve_at([1.0, 2.0], [0.2, 0.4], 0.5) == pytest.approx(0.1)  # from (0, 0)
    assert _curve_at([1.0, 2.0], [0.2, 0.4], 9.0) == pytest.approx(0.4)  # flat after the end
    assert parse_candidate("fast:lr=0.04+hflip=0.5") == ("fast", {"lr": 0.04, "hflip": 0.5})
    assert parse_candidate("w:model=width=0.25") == ("w", {"model": ("width=0.25",)})  # replaces the base width
    assert parse_candidate("s:model=bev.output_stride=16") == ("s", {"model": ("width=0.5", "bev.output_stride=16")})
    for bad, needle in [("lr=0.04", "expected NAME:FIELD=VALUE"), ("x:batch_size=3", "FIELD one of"), ("x:lr", "FIELD one of")]:
        with pytest.raises(UserError, match=needle):
            parse_candidate(bad)


def test_cli_refuses_a_bad_candidate_in_one_line(data, tmp_path, capsys):
    assert main(["bench", "recipe", str(data), "--out", str(tmp_path / "r"), "--candidate", "x:batch_size=3"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1 and "FIELD one of" in err


def _rows(**curves):
    return {n: {"curve": [{"epoch": i + 1, "core_hours": x, "map_vehicles": y} for i, (x, y) in enumerate(c)]}
            for n, c in curves.items()}


def test_aim_is_the_first_crossing_or_a_labelled_log_linear_extrapolation_of_the_frontier():
    rows = _rows(short=[(0.5, 0.05), (1.0, 0.10)], long=[(0.5, 0.04), (1.0, 0.12), (2.0, 0.30)])
    a = aim_reached(rows, 0.2)
    # long crosses 0.2 between (1.0, 0.12) and (2.0, 0.30): 1 + 0.08 / 0.18
    assert a["reached"] and a["by"] == "long" and a["core_hours"] == pytest.approx(1 + 0.08 / 0.18, abs=1e-4)
    assert a["per_candidate_core_hours"]["short"] is None
    assert a["per_candidate_stays_from_core_hours"] == {"short": None, "long": 2.0}
    noisy = aim_reached(_rows(n=[(1.0, 0.3), (2.0, 0.1), (3.0, 0.25), (4.0, 0.3)]), 0.2)
    assert noisy["core_hours"] == pytest.approx(2 / 3, abs=1e-4)  # touches it first ...
    assert noisy["per_candidate_stays_from_core_hours"]["n"] == 3.0  # ... and stays from the third epoch
    assert [f["candidate"] for f in a["frontier"]] == ["short", "long"]  # the ends, by cost
    b = aim_reached(rows, 0.5)  # ends (1 h, 0.10) and (2 h, 0.30): +0.20 a doubling -> one more doubling
    assert not b["reached"] and b["best_map_vehicles"] == 0.3 and b["gain_per_doubling"] == pytest.approx(0.2)
    assert b["extrapolated_core_hours"] == pytest.approx(4.0) and "guess" in b["extrapolation"]
    flat = aim_reached(_rows(a=[(1.0, 0.2)], b=[(2.0, 0.1)]), 0.5)  # more CPU bought less: no extrapolation
    assert not flat["reached"] and flat["gain_per_doubling"] < 0 and "extrapolated_core_hours" not in flat
    assert aim_reached(_rows(a=[(1.0, 0.0), (2.0, 0.3)]), 0.15)["core_hours"] == pytest.approx(1.5)


def test_candidates_with_their_own_epochs_trace_the_budget_frontier(data, tmp_path):
    cands = {"1 epoch": {"epochs": 1, "model": ("width=0.25",)}, "2 epochs": {"epochs": 2, "model": ("width=0.25",)}}
    r = bench_recipe(str(data), tmp_path / "b", "radar", cands, epochs=5, threads=1, bootstrap=0, progress=False,
                     aim=0.9)
    assert [len(c["curve"]) for c in r["candidates"].values()] == [1, 2]
    for name, n in (("1 epoch", 1), ("2 epochs", 2)):
        assert json.loads((tmp_path / "b" / name.replace(" ", "_") / "config.json").read_text())["epochs"] == n
    assert r["aim"] == aim_reached(r["candidates"], 0.9)
    with pytest.raises(UserError, match="epochs must be a whole number"):
        bench_recipe(str(data), tmp_path / "c", "radar", {"x": {"epochs": 0}}, progress=False)
    with pytest.raises(UserError, match="--aim"):
        bench_recipe(str(data), tmp_path / "c", "radar", {"x": {}}, aim=1.5, progress=False)
