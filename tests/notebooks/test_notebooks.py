"""The teaching notebooks run top to bottom (nbclient), so they cannot rot; the degradation-physics notebook's
fitted coefficients are held to the laws it teaches. They are stored executed, with their figures, so a
reader sees them on GitHub (`python notebooks/execute.py` stores them; docs/notebooks.md): the stored
outputs are checked for shape here, never compared with a run's, and each run starts from cleared outputs.

The fusion-theory notebook reads its simulated measurements from $HYDRABENCH_CACHE/theory, pointed
here at the session's shared cache: whichever of this test and tests/study/test_theory_measured.py
runs first measures study.experiments.theory.SMALL_CONFIG and the fog bank, the other reads them.
"""

import json
import math
import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[2]


def run_notebook(name: str, monkeypatch, cache_root: Path, stop_before: str | None = None):
    """Run notebook `name` top to bottom, or up to the markdown cell that starts with `stop_before`
    (what a test does not read, and another test runs)."""
    monkeypatch.setenv("HYDRABENCH_CACHE", str(cache_root))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(ROOT / "notebooks" / name, as_version=4)
    if stop_before is not None:
        cut = [i for i, c in enumerate(nb.cells) if c.cell_type == "markdown" and c.source.startswith(stop_before)]
        assert len(cut) == 1, f"{name}: no one markdown cell starts with {stop_before!r}"
        nb.cells = nb.cells[:cut[0]]
    for cell in nb.cells:  # the stored outputs: what this run asserts on must be its own
        if cell.cell_type == "code":
            cell.outputs, cell.execution_count = [], None
    client = NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}})
    client.execute()  # raises CellExecutionError, naming the cell, if any cell fails
    return nb


def test_fusion_theory_notebook_runs_and_draws_its_figures(monkeypatch, shared_cache, cache_lock):
    with cache_lock("theory"):
        nb = run_notebook("01_fusion_theory.ipynb", monkeypatch, shared_cache)
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    figures = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(figures) >= 5
    text = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
    assert "fog (layout motorway)" in text and "night (layout motorway)" in text
    assert not [o for o in outputs if o.get("output_type") == "error"]


def fitted_coefficients(nb) -> dict:
    """The notebook's `FITS` dictionary, printed as one 'FITS {json}' line by its last cell."""
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
                   if o.get("output_type") == "stream")
    lines = [line for line in text.splitlines() if line.startswith("FITS ")]
    assert len(lines) == 1, "the notebook prints its fitted coefficients once"
    return json.loads(lines[0][len("FITS "):])


def test_degradation_physics_notebook_measures_each_law_on_twins(monkeypatch, shared_cache):
    """02_degradation_physics renders twins of one scene and fits each degradation law to what the simulated
    sensors output; the laws are restated here, independently of the library's constants:

    - camera, fog (Koschmieder, MOR at the 5 % contrast threshold): beta = ln 20 / MOR, fitted on the 8-bit
      images within 1 % (measured: < 0.1 %);
    - lidar, fog: P' = P exp(-2 alpha R), alpha = ln 20 / MOR, fitted on the kept returns within 1e-4 for both
      fog models; our model keeps exactly the returns the law keeps except those a fog point replaces, and
      neither model keeps a return the law loses;
    - radar, rain: ITU-R P.838-3 at 77 GHz, gamma = 1.13 R^0.72 dB/km over the two-way path, fitted on the
      8-bit polar images within 3 % at 25-50 mm/h and 5 % at 10 mm/h (measured: < 2 %) and within 3 standard
      errors at 1 mm/h (a fifth of a count over 100 m); fog (ITU-R P.840) within 3 standard errors, under 1 dB two-way over 100 m;
    - camera, night: the photon-transfer slope gives back the recorded analogue gain within 10 % (measured:
      < 4 %), the gain never exceeds 4 and reaches it at night; the road patch's level within 5 % and its
      noise std within 10 % of Poisson + 4 e- read noise; the image's log-average within 5 % of g k L_bar from
      1 lx up (below, the sensor floor lifts it).
    """
    nb = run_notebook("02_degradation_physics.ipynb", monkeypatch, shared_cache)
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert len([o for o in outputs if "image/png" in o.get("data", {})]) >= 5  # gallery, camera, lidar, radar, night
    fits = fitted_coefficients(nb)

    camera = fits["camera_beta_per_m"]
    assert {600.0, 40.0} <= {round(f["mor_m"]) for f in camera.values()}
    for f in camera.values():
        assert f["fit"] == pytest.approx(math.log(20) / f["mor_m"], rel=0.01)
    # the clear twin shares the fog frame's overcast sky, so it is as good a reference; a sunlit one is not
    other = fits["camera_beta_other_references"]
    assert all(abs(v) < 0.01 for k, v in other.items() if k.startswith("the clear twin"))
    assert other["the same moment sunlit, MOR 600 m"] < -0.1

    for key, f in fits["lidar_alpha_per_m"].items():
        alpha = math.log(20) / f["mor_m"]
        assert f["ours"] == pytest.approx(alpha, rel=1e-4) and f["hahner"] == pytest.approx(alpha, rel=1e-4)
        c = fits["lidar_counts"][key]
        assert c["ours_lost_of_law_kept"] == 0 and c["ours_kept_beyond_law"] == 0 and c["hahner_kept_beyond_law"] == 0
        assert c["ours_kept"] + c["ours_fog_of_law_kept"] == c["law_kept"]
    by_mor = sorted(fits["lidar_counts"].items(), key=lambda kv: -fits["lidar_alpha_per_m"][kv[0]]["mor_m"])
    fog_points = [c["ours_fog_of_law_kept"] for _, c in by_mor]
    assert fog_points == sorted(fog_points) and fog_points[-1] > 10 * fog_points[0]  # denser fog, more fog points

    for f in fits["radar_gamma_db_per_km"].values():
        law = 1.13 * f["rain_mm_h"] ** 0.72
        assert f["law"] == pytest.approx(law, rel=1e-3)
        if f["rain_mm_h"] >= 25:  # 1-4 dB over 100 m: a 5 % error in the law fails here
            assert f["fit"] == pytest.approx(law, rel=0.03)
        elif f["rain_mm_h"] >= 10:
            assert f["fit"] == pytest.approx(law, rel=0.05)
        else:
            assert abs(f["fit"] - law) < 3 * f["se"]
    fog = fits["radar_fog_gamma_db_per_km"]
    liquid_water = 0.05 * (fog["mor_m"] / 300.0) ** (-math.log(10) / math.log(6))  # g/m^3, through P.840's points
    assert fog["law"] == pytest.approx(3.2 * liquid_water, rel=1e-3)  # P.840 at 77 GHz: 3.2 dB/km per g/m^3
    assert abs(fog["fit"] - fog["law"]) < 3 * fog["se"] and 2 * fog["fit"] * 0.1 < 1.0  # < 1 dB over 100 m and back

    night = fits["night"]
    assert max(f["gain"] for f in night.values()) == 4.0 and min(f["gain"] for f in night.values()) == 1.0
    for f in night.values():
        if f["gain_ptc"] is not None:
            assert f["gain_ptc"] == pytest.approx(f["gain"], rel=0.10), f
        assert f["road_mean"] == pytest.approx(f["road_mean_law"], rel=0.05), f
        assert f["road_std"] == pytest.approx(f["road_std_law"], rel=0.10), f
        if f["lux"] >= 1.0:
            assert f["key"] == pytest.approx(f["key_law"], rel=0.05), f
    assert sum(f["gain_ptc"] is not None for f in night.values()) >= 6


def test_selective_fusion_notebook_reads_a_tiny_study_and_answers_its_three_questions(monkeypatch, shared_cache,
                                                                                      cache_lock):
    """03 on the tiny study (configs/study/tiny.yaml), shared with tests/study/test_study_runner.py:
    whichever runs first runs the study, the other finds every stage done."""
    from study.pipeline.stages import run_study
    from study.pipeline.config import load_study_config

    cache = shared_cache
    study = Path(os.environ.get("HYDRABENCH_TINY_STUDY") or cache / "study-tiny")
    with cache_lock("study-tiny"):
        run_study(load_study_config("tiny"), study, progress=False)
    monkeypatch.setenv("HYDRABENCH_STUDY", str(study))
    # section 4 (the committed reference model on a fresh dataset) does not read the study: the test
    # of 03 on the committed cpu study below runs it
    nb = run_notebook("03_selective_fusion.ipynb", monkeypatch, cache, stop_before="## 4.")
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    figures = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(figures) >= 3  # selection per context, loss against energy, selection minus late fusion
    text = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
    assert "THESE NUMBERS MEAN NOTHING" in text and "scale tiny" in text
    assert "hydrafusion / optimal" in text and "ecofusion / loss_based" in text  # what each gate picks
    # why: the knowledge gate's table rows; it reads the context label, each condition at severity 3
    assert "fog (severity 4; the gate reads the label, at severity 3): ranking" in text
    assert "lambda_E 0 -> 1" in text and "selection - late" in text and "hurts in" in text


def test_when_to_drop_a_sensor_notebook_derives_the_crossover_and_reads_a_studys(monkeypatch, shared_cache,
                                                                                  cache_lock):
    """04 on the tiny study: the covariance argument's crossover in closed form equals its Monte Carlo
    check (the notebook asserts it within 5 %), and the study's measured crossovers and physical gate
    are read and shown. The visibility is restated here: r2* = r1 + 2 r2_hat, MOR* = 6 d / ln(r2* / r2_hat)."""
    from study.pipeline.stages import run_study
    from study.pipeline.config import load_study_config

    study = Path(os.environ.get("HYDRABENCH_TINY_STUDY") or shared_cache / "study-tiny")
    with cache_lock("study-tiny"):
        run_study(load_study_config("tiny"), study, progress=False)
    monkeypatch.setenv("HYDRABENCH_STUDY", str(study))
    nb = run_notebook("04_when_to_drop_a_sensor.ipynb", monkeypatch, shared_cache)
    assert not [o for o in _outputs(nb) if o.get("output_type") == "error"]
    assert len([o for o in _outputs(nb) if "image/png" in o.get("data", {})]) >= 3  # WLS worth, crossovers, strength
    text = "".join(o.get("text", "") for o in _outputs(nb) if o.get("output_type") == "stream")
    mor = 6 * 40.0 / math.log((1.0 + 2 * 0.25) / 0.25)
    assert f"MOR* = {mor:.1f} m" in text and "THESE NUMBERS MEAN NOTHING" in text
    assert "late: with minus without each sensor" in text and "camera in fog, all_branches: measured" in text
    assert "physical_gate" in text and "hydrafusion:knowledge" in text
    # section 4 reads the committed PEM sweep and known-answer records (docs/pem.md checks their numbers)
    for title in ("knowledge gate", "per-context constant", "physical gate", "room for context (split-sample)",
                  "a-posteriori oracle"):  # every comparison of the sweep, drawn and read
        assert f": {title}" in text and "resolved above at strengths" in text, title
    assert "physical_gate" in text.split("construction holds on the test frames", 1)[1]
    assert "construction holds on the test frames: True" in text and "context_constant" in text
    assert "recovers the rule" in text and "does not recover the rule" in text


def test_bring_your_own_detector_notebook_scores_the_classical_detectors_and_a_rule_gate(monkeypatch, shared_cache,
                                                                                       shared_dataset):
    """05 on the 8-frame junction/fog dataset tests/examples and tests/study/test_external.py use
    (HYDRABENCH_BYOD_DATA): it exports it, runs both example detectors, scores them, the weather gates
    and the context oracle, and reads the committed record of the demo set."""
    from sensors.generate import GenerateConfig

    data = shared_dataset(GenerateConfig(contexts=("junction", "fog"), frames_per_context=4, sequence_length=2, seed=9))
    monkeypatch.setenv("HYDRABENCH_BYOD_DATA", str(data))
    monkeypatch.setenv("HYDRABENCH_BYOD_BOOTSTRAP", "50")
    nb = run_notebook("05_bring_your_own_detector.ipynb", monkeypatch, shared_cache)
    assert not [o for o in _outputs(nb) if o.get("output_type") == "error"]
    # the frames, per context, the demo set's record, and its classical detectors against the networks
    assert len([o for o in _outputs(nb) if "image/png" in o.get("data", {})]) >= 4
    text = "".join(o.get("text", "") for o in _outputs(nb) if o.get("output_type") == "stream")
    assert "$ hydrabench export nuscenes" in text and "$ python examples/lidar_detector.py" in text
    assert "8 frames -> 4 scenes, 8 samples" in text and "8 frames, classes merged" in text
    for method in ("single:lidar", "single:radar", "late", "selection:weather_radar", "selection:weather_add_radar",
                   "selection:context_oracle"):
        assert f"\n{method} " in text, method
    assert "--gate examples.weather_gate:switch_to_radar: the same choice as weather_radar.json on 8 of 8 frames" in text
    assert "junction  best fixed: single:lidar" in text and "selection:context_oracle minus late:" in text
    assert "results/classical_detectors_" in text and ": 192 frames," in text
    assert "cpu-frontier lidar branch" in text and "the classical one is above in:" in text


def _outputs(nb) -> list:
    return [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]


@pytest.mark.parametrize("name, figures", [("01_fusion_theory.ipynb", 5), ("02_degradation_physics.ipynb", 5),
                                           ("03_selective_fusion.ipynb", 3), ("04_when_to_drop_a_sensor.ipynb", 3),
                                           ("05_bring_your_own_detector.ipynb", 4)])
def test_notebooks_are_stored_executed_with_their_figures(name, figures):
    """Stored as one top-to-bottom run: every code cell executed in order, its figures as PNG, no error, no
    per-cell timing metadata (a diff of a rerun shows what changed, not when), a size GitHub renders."""
    path = ROOT / "notebooks" / name
    nb = nbformat.read(path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert [c.execution_count for c in code] == list(range(1, len(code) + 1)), "run notebooks/execute.py"
    outputs = _outputs(nb)
    assert len([o for o in outputs if "image/png" in o.get("data", {})]) >= figures
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert not [c for c in nb.cells if "execution" in c.metadata]
    assert set(nb.metadata) <= {"kernelspec", "language_info"}
    assert path.stat().st_size < 3_000_000


def test_selective_fusion_notebook_is_stored_on_the_committed_cpu_study_and_runs_on_it(monkeypatch, shared_cache):
    """03's default study is results/study_cpu (a report without its trained run): stored on it, and it still
    runs on it, printing the Knowledge gate's table rows where a study has no run to explain frames with."""
    stored = "".join(o.get("text", "") for o in _outputs(nbformat.read(ROOT / "notebooks" / "03_selective_fusion.ipynb",
                                                                        as_version=4)))
    assert "study results/study_cpu: scale cpu" in stored and "MEAN NOTHING" not in stored
    monkeypatch.delenv("HYDRABENCH_STUDY", raising=False)
    nb = run_notebook("03_selective_fusion.ipynb", monkeypatch, shared_cache)
    text = "".join(o.get("text", "") for o in _outputs(nb) if o.get("output_type") == "stream")
    assert "study results/study_cpu: scale cpu" in text and "MEAN NOTHING" not in text
    assert "holds the report, not the trained run" in text and "fog (motorway layout + fog):" in text
    assert len([o for o in _outputs(nb) if "image/png" in o.get("data", {})]) >= 3
    # section 4: the committed reference model against late fusion on a freshly generated dataset
    assert "cpu-ref: 19.1 M parameters" in text and "gates attention, deep" in text
    for method in ("late", "all_branches", "hydrafusion:deep", "hydrafusion:attention", "hydrafusion:optimal"):
        assert f"\n{method} " in text, method
    assert "16 frames (all), 8 sequences" in text
