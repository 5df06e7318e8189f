"""`hydrabench study`: the whole HydraFusion + EcoFusion comparison as cached, resumable stages.

    generate -> train -> gatedata -> gates -> crossover -> evaluate -> pem -> transitions -> report

(crossover only with a `crossover` section: the severity sweep on a set of its own, whose measured
crossovers give the evaluation's physical knowledge gate its rules; transitions only with a
`transitions` section: the learned gates with memory on sequences whose weather ramps; issue 37. pem
only with a `pem` section: a perception error model fitted on the gate frames, the verdict swept over
detector strength; issue 49.)

Each stage is a function of its config section (`StudyConfig`) and of the digests of the stages it
reads. Its key is the SHA-256 of both; its output lives in `DIR/stages/<stage>-<key>/` with a
`manifest.json` (the key, what it was made of, its output digest, the seconds it took). A stage
works in `DIR/stages/<stage>-<key>.partial/` and is renamed to its final name when complete, so:

- a stage whose final directory exists (same key) is skipped: a second run does no work;
- killed anywhere (even kill -9), the next run continues in the partial directory: generation
  completes its missing shards, training resumes from its last checkpoint (`study.engine.train`), the gate
  datasets from their last chunk, gate training from its last epoch; evaluation starts again;
- a changed field changes the key of its stage and of every stage below it (their inputs' digests
  change), and only those run again; the stages above keep theirs. Old keys stay in DIR/stages as
  a cache (delete them to reclaim the space).

Stages below `train` work on a *farm* of the run directory: the upstream run's directories are
recreated and its files symlinked (relative links), so what a stage writes (gate caches, gates,
latency tables) lands in its own directory and never changes a finished stage.

Beside its config section and its inputs, a stage's key holds everything else its output depends
on (`stage_identity`): the code it runs (`study.engine.code_identity.code_digest` of its modules and of
its stage function), the sensor model version and the sensor profile (generate), the model
profile's contents (train), and the device type and precision the networks run in
(`study.engine.device.compute_identity`; generation always runs on the CPU). Each key also holds the key of
every stage it reads, so a change reruns exactly its stage and the stages below it. Threads,
workers and backend are part of no key: they decide how fast a stage runs, not what it computes.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

from sim.config import to_dict
from sim.errors import UserError
from study.engine.gate_data import file_sha256
from study.outputs import atomic_path, write_json_atomic
from study.pipeline.cache import StageRecord, Study, json_digest, link_farm

if TYPE_CHECKING:  # the config imports torch (TrainConfig); `hydrabench study --help` reads STAGES from here
    from study.pipeline.config import GatesSection, StudyConfig, TrainSection

STAGES = ("generate", "train", "gatedata", "gates", "crossover", "evaluate", "pem", "transitions", "report")


def _device_setup(cfg: StudyConfig):
    """The training stage's device choice (`run.amp`; by default bf16 autocast on CUDA, fp32 on the
    CPU); the stages after it run their networks in fp32 (`_eval_setup`)."""
    from study.engine.device import resolve_device

    return resolve_device(device=cfg.run.device, threads=cfg.run.threads,
                          amp=None if cfg.run.amp == "default" else cfg.run.amp)


def _eval_setup(setup):
    """The same device without autocast: gate data, gates and evaluation are fp32 numbers."""
    import dataclasses

    return dataclasses.replace(setup, amp=False)


def eco_settings(cfg: StudyConfig):
    from study.eco.data import EcoSettings

    return EcoSettings(fusion=cfg.gates.fusion, power=cfg.evaluate.power, energy_scale=cfg.evaluate.energy_scale, loss_scale=cfg.evaluate.loss_scale,
                       rule=cfg.evaluate.rule, batch_size=cfg.train.batch_size, max_frames=cfg.gates.eco_max_frames)


# ----- the stages: each a function of its work directory and its inputs ----------------------


def generate_stage(work: Path, gcfg, workers: int, backend: str, progress: bool) -> tuple[str, dict]:
    """The dataset (`sensors.generate`) in work/data."""
    from sensors.generate import generate

    generate(gcfg, work / "data", workers=workers, progress=progress, backend=backend)
    manifest = work / "data" / "manifest.json"
    return file_sha256(manifest), {"frames": len(json.loads(manifest.read_text())["frames"])}


def _paper_view(tr: StageRecord, inputs: dict, gen: StageRecord) -> StageRecord:
    """The train stage as the gate stages read it: the paper's branches alone. With
    `train.early_fusion` its record is the key and digest the train stage would have without the
    early-fusion model (the same inputs with early_fusion false and no train.early_detectors), so
    that adding, adopting or retraining the early-fusion model reruns only the evaluation, never the
    gate data and gates of the same paper detectors. Without early fusion it is the train stage."""
    t = inputs["train"]
    if not t.get("early_fusion") or "paper" not in tr.manifest.get("checkpoints_sha256", {}):
        return tr  # (a train stage that recorded no checkpoint digests: read whole, as before)
    paper_only = {**inputs, "train": {k: v for k, v in {**t, "early_fusion": False}.items() if k != "early_detectors"}}
    paper_only = {k: v for k, v in paper_only.items() if k != "early_detectors_sha256"}
    key = Study.key("train", {**paper_only, "upstream": {gen.name: {"key": gen.key, "digest": gen.digest}}})
    paper_sha = tr.manifest["checkpoints_sha256"]["paper"]
    return StageRecord(tr.name, key, tr.dir, tr.status, tr.seconds, json_digest({"paper": paper_sha}), tr.manifest)


def train_stage(work: Path, data: Path, train_cfg: TrainSection, profile: str, setup, say,
                progress: bool) -> tuple[str, dict]:
    """The paper's branches in work/paper and, with early_fusion, the early-fusion models in work/early."""
    from study.engine.train import TrainConfig, train

    t = train_cfg
    runs = {"paper": ("paper", t.branches)}
    if t.early_fusion:
        runs["early"] = ("early_fusion", t.early_branches)
    digests = {}
    adopted = {"paper": t.detectors, "early": t.early_detectors if t.early_fusion else ""}
    for name, spec in adopted.items():
        if spec:
            say(f"train: {name} (adopting the detectors of {spec}: nothing to train)")
            adopt_detectors(spec, data, work / name, runs[name][1])
            digests[name] = file_sha256(work / name / "checkpoint.pt")
            runs.pop(name)
    for name, (bset, branches) in runs.items():
        say(f"train: {name} ({bset} branch set)")
        tc = TrainConfig(data=str(Path(data).resolve()), model_profile=profile, branch_set=bset,
                         branches=tuple(branches), epochs=t.epochs, batch_size=t.batch_size, lr=t.lr,
                         warmup_steps=t.warmup_steps, clip_grad=t.clip_grad, seed=t.seed,
                         checkpoint_steps=t.checkpoint_steps, eval_frames=t.eval_frames, threads=setup.threads,
                         protocol=t.protocol, device=setup.device, amp=setup.amp, workers=setup.workers,
                         gate_holdout=t.gate_holdout, model=tuple(t.model),
                         init_from=_init_from(t.init_from) if name == "paper" else "")
        train(tc, work / name, progress=progress)
        digests[name] = file_sha256(work / name / "checkpoint.pt")
    return json_digest(digests), {"checkpoints_sha256": digests}


def adopt_detectors(spec: str, data: Path, out: Path, branches) -> None:
    """Copy the detectors of `spec` (train.detectors or train.early_detectors: a reference model or a
    training run) into the run
    directory `out` (config.json and checkpoint.pt; atomic), after checking that they were trained on
    `data` (`study.pipeline.checks.check_adopted`). The copied config names `data` and where the weights
    came from."""
    import shutil

    from sensors.dataset import read_manifest
    from study.pipeline.checks import check_adopted, detectors_run

    src = detectors_run(spec, "train.detectors" if out.name == "paper" else "train.early_detectors")
    cfg = check_adopted(src, read_manifest(data)["config"], branches)
    if (out / "checkpoint.pt").is_file() and file_sha256(out / "checkpoint.pt") == file_sha256(src / "checkpoint.pt"):
        return
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "checkpoint.pt") as tmp:
        shutil.copyfile(src / "checkpoint.pt", tmp)
    write_json_atomic(out / "config.json", {**cfg, "data": str(Path(data).resolve()), "adopted_from": str(spec)})


def _init_from(text: str) -> str:
    """train.init_from -> the run directory TrainConfig.init_from takes ("" stays "")."""
    if not text:
        return ""
    from study.engine.reference_model import resolve_run

    run = resolve_run(text)
    if not (run / "checkpoint.pt").is_file():
        raise UserError(f"train.init_from {text!r}: neither a reference model (models/) nor a training run")
    return str(run.resolve())


def study_data(work: Path, parts: dict[str, Path]) -> Path:
    """The dataset a stage reads: the detectors' own when the study has no gate or test set, else the
    view of its `parts` {name: dataset} in work/data (`sensors.combine`: links to the parts' shards,
    relative, so they hold when the stage's folder is renamed beside the parts')."""
    if list(parts) == ["detectors"]:
        return Path(parts["detectors"])
    from sensors.combine import combine

    combine(parts, work / "data")
    return work / "data"


def gatedata_stage(work: Path, run_paper: Path, parts: dict[str, Path], settings, batch_size: int, setup,
                   progress: bool, val_fraction: float = 0.15, seed: int = 0) -> tuple[str, dict]:
    """HydraFusion's gate dataset and EcoFusion's, cached under work/run (a farm of the paper run), on
    the detectors' data and the gate set (no test set: the gates stage never reads it)."""
    from study.eco.data import build_eco_data
    from study.engine.gate_data import GateData
    from study.engine.scoring import frames_for, load_run

    data = study_data(work, parts)
    run = work / "run"
    link_farm(run_paper, run)
    model, run_cfg = load_run(run, "latest", device=setup.device)
    train_idx, _ = frames_for(run_cfg, data, "train")
    gate_idx, _ = frames_for(run_cfg, data, "gate")
    test_idx, _ = frames_for(run_cfg, data, "test")  # never a test set's: the gate data's view holds none
    gd = GateData(run, data, model)
    gd.ensure(sorted(train_idx + gate_idx + test_idx), batch_size=batch_size, progress=progress)
    eco = build_eco_data(run, data, settings, progress=progress, device=setup.device, val_fraction=val_fraction,
                         seed=seed)
    return json_digest({"gate_data": gd.key, "eco_data": Path(eco["eco_data"]).name}), {
        "gate_data_key": gd.key, "eco_data": eco}


def gates_stage(work: Path, gatedata_run: Path, data: Path, gates: GatesSection, settings, setup, say,
                progress: bool, k: int = 1) -> tuple[str, dict]:
    """The learned HydraFusion and EcoFusion gates and the latency table, under work/run. `k`: the
    branches HydraFusion's gates run in the evaluation (`evaluate.k`): their epoch and objective are
    chosen by the validation regret of their top k (`GateTrainConfig.k`). EcoFusion's gates choose
    one configuration: k = 1."""
    import dataclasses

    from study.eco.config_gate_study import train_eco_gate
    from study.eco.latency_energy import energy_table
    from study.engine.gate_training import GateTrainConfig, train_gate

    g = gates
    run = work / "run"
    link_farm(gatedata_run, run)
    from study.engine.gate_training import IN_SAMPLE
    from study.engine.scoring import frames_for

    run_cfg = json.loads((run / "config.json").read_text())
    compare = g.compare_targets and g.targets != "train" and bool(frames_for(run_cfg, data, "gate")[0])
    out, digests = {}, {}
    for gate in g.gates:
        gate_cfg = GateTrainConfig(gate=gate, epochs=g.epochs, batch_size=g.batch_size, lr=g.lr,
                                   val_fraction=g.val_fraction, seed=g.seed, threads=setup.threads, targets=g.targets,
                                   context=g.context, pooling=g.pooling, k=k)
        in_sample = dataclasses.replace(gate_cfg, targets="train")
        say(f"gates: HydraFusion {gate} gate")
        out[f"hydra_{gate}"] = train_gate(run, data, gate_cfg, progress=progress, setup=setup)
        digests[f"hydra_{gate}"] = file_sha256(run / "gates" / gate / "gate.pt")
        for n in sorted(c for c in g.curve if c < out[f"hydra_{gate}"]["train_frames"]):
            say(f"gates: HydraFusion {gate} gate on {n} of the fitting frames (the learning curve)")
            d = run / "gates" / gate / "curve" / str(n)
            out[f"hydra_{gate}_curve_{n}"] = train_gate(run, data, dataclasses.replace(gate_cfg, fit_frames=n),
                                                        progress=progress, setup=setup, out=d)
            digests[f"hydra_{gate}_curve_{n}"] = file_sha256(d / "gate.pt")
        if compare:
            say(f"gates: HydraFusion {gate} gate on the detectors' training frames (the comparison)")
            d = run / "gates" / gate / IN_SAMPLE
            out[f"hydra_{gate}_{IN_SAMPLE}"] = train_gate(run, data, in_sample, progress=progress, setup=setup, out=d)
            digests[f"hydra_{gate}_{IN_SAMPLE}"] = file_sha256(d / "gate.pt")
        say(f"gates: EcoFusion {gate} gate")
        out[f"eco_{gate}"] = train_eco_gate(run, data, gate, gate_cfg, settings, progress=progress)
        digests[f"eco_{gate}"] = file_sha256(run / "eco" / "gates" / gate / "gate.pt")
        if compare:
            say(f"gates: EcoFusion {gate} gate on the detectors' training frames (the comparison)")
            d = settings.gate_dir(run, gate) / IN_SAMPLE
            out[f"eco_{gate}_{IN_SAMPLE}"] = train_eco_gate(run, data, gate, in_sample, settings, progress=progress,
                                                          out=d)
            digests[f"eco_{gate}_{IN_SAMPLE}"] = file_sha256(d / "gate.pt")
    say("gates: latency and energy of every configuration")
    energy = energy_table(run, data, settings, threads=1, repeats=g.energy_repeats, frames=g.energy_frames,
                          progress=progress, n_check=g.energy_check)
    energy = {k: v for k, v in energy.items() if not k.startswith("_")}
    digests["latency"] = file_sha256(run / "eco" / "latency.json")
    say("gates: each learned gate's own decision time")
    energy["gate_latency"] = measure_gates(run, data, g, settings, setup, progress)
    digests["gate_latency"] = file_sha256(run / "eco" / "gate_latency.json")
    return json_digest(digests), {"gates": out, "energy": energy}


def measure_gates(run: Path, data: Path, g: GatesSection, settings, setup, progress: bool) -> dict:
    """Each learned gate's own decision time on the latency frames (`study.eco.latency_energy.gate_latency`,
    one thread as the latency table): HydraFusion's and EcoFusion's."""
    from study.eco.config_gate_study import load_eco_gate
    from study.eco.data import eco_splits, open_eco_run
    from study.eco.latency_energy import gate_latency
    from study.engine.gate_training import load_trained_gate

    model, cfg, configs, ed = open_eco_run(run, data, settings, 1)
    _train, test = eco_splits(cfg, data, settings.max_frames)
    gates = {}
    for gate in g.gates:
        gates[f"hydrafusion:{gate}"] = load_trained_gate(run, gate, model)
        gates[f"ecofusion:{gate}"] = load_eco_gate(run, gate, model, configs, ed, settings)
    return gate_latency(run, data, gates, test[:g.energy_frames], repeats=g.energy_repeats, threads=1,
                        progress=progress)


def crossover_stage(work: Path, run_paper: Path, cfg: StudyConfig, setup, progress: bool) -> tuple[str, dict]:
    """The severity sweep on its own sweep set (`study.experiments.crossover`) -> work/crossover.json and
    its figures."""
    from study.experiments.crossover import run_crossover

    rec = run_crossover(work, run_paper, cfg.crossover, cfg.profile, cfg.crossover.fusion, setup, cfg.run.workers,
                        cfg.run.backend, cfg.train.batch_size, progress)
    return file_sha256(work / "crossover.json"), {"frames": rec["frames"], "figures": rec["figures"]}


def evaluate_stage(work: Path, gates_run: Path, run_early: Path | None, parts: dict[str, Path], cfg: StudyConfig,
                   settings, setup, progress: bool, crossover: Path | None = None) -> tuple[str, dict]:
    """Every method on the test split or the test set (`study.pipeline.evaluation`) -> work/results.json (with
    the device type and precision it ran in); with the crossover stage's record, the physical
    knowledge gate too."""
    from study.engine.device import compute_identity
    from study.pipeline.evaluation import evaluate_study

    data = study_data(work, parts)
    run = work / "run"
    link_farm(gates_run, run)
    cross = json.loads(Path(crossover).read_text()) if crossover is not None else None
    res = evaluate_study(run, run_early, data, cfg, settings, work, setup=setup, progress=progress, crossover=cross)
    res["compute"] = compute_identity(setup)
    write_json_atomic(work / "results.json", res, default=str)
    return file_sha256(work / "results.json"), {}


def pem_inputs(cfg: StudyConfig) -> dict:
    """The config part of the pem stage's key: its section, the gate frames' validation split it chooses on
    (`gates.val_fraction`, `gates.seed`), the knowledge gate's k and the prediction pass's batch size."""
    return {"pem": to_dict(cfg.pem), "gate_frames": {"val_fraction": cfg.gates.val_fraction, "seed": cfg.gates.seed},
            "k": _gates_k(cfg), "batch_size": cfg.train.batch_size}


def pem_stage(work: Path, run_paper: Path, parts: dict[str, Path], cfg: StudyConfig, setup,
              progress: bool) -> tuple[str, dict]:
    """The verdict over detector strength (`study.experiments.pem_section`): a PEM fitted on the detectors'
    predictions on the gate frames' fitting sequences, swept over `pem.strengths` on the test frames ->
    work/pem.json and work/pem_sweep.png."""
    from study.experiments.pem_section import run_pem_section

    data = study_data(work, parts)
    rec = run_pem_section(work, run_paper, data, cfg.pem, val_fraction=cfg.gates.val_fraction,
                          val_seed=cfg.gates.seed, k=_gates_k(cfg), batch_size=cfg.train.batch_size, setup=setup,
                          progress=progress)
    return file_sha256(work / "pem.json"), {"fit_frames": rec["fit"]["frames"], "seconds": rec["seconds"]}


def transitions_inputs(cfg: StudyConfig) -> dict:
    """The config part of the transitions stage's key: its section, the profile, the batch size and the
    evaluation's power model and energy scale (its energy per variant)."""
    return {"transitions": to_dict(cfg.transitions), "profile": cfg.profile, "batch_size": cfg.train.batch_size,
            "energy": {"power": cfg.evaluate.power, "scale": cfg.evaluate.energy_scale}}


def transitions_stage(work: Path, gates_run: Path, cfg: StudyConfig, setup, progress: bool,
                      gate_data: Path | None = None) -> tuple[str, dict]:
    """The learned gates with memory on the transition set (`study.experiments.transitions`) ->
    work/transitions.json and its figures; the recurrent gate trains on `gate_data` (the gate set the
    gates stage fitted on)."""
    from study.experiments.transitions import run_transitions

    link_farm(gates_run, work / "run")
    rec = run_transitions(work, work / "run", cfg.transitions, tuple(cfg.gates.gates), cfg.profile, setup,
                          cfg.run.workers, cfg.run.backend, cfg.train.batch_size, progress, gate_data=gate_data,
                          gates=cfg.gates, settings=eco_settings(cfg))
    return file_sha256(work / "transitions.json"), {"frames": rec["frames"], "figures": rec["figures"]}


def report_stage(work: Path, results_dir: Path, context: dict, rel_to: Path,
                 transitions: Path | None = None, pem: Path | None = None) -> tuple[str, dict]:
    """report.md, report.html and report.json of the evaluation's results (and of the transitions and
    pem stages', when the study has them)."""
    from study.report.build import write_report

    results = json.loads((Path(results_dir) / "results.json").read_text())
    for name, path in (("transitions", transitions), ("pem", pem)):
        if path is not None:
            results[name] = json.loads(Path(path).read_text())
            results[name]["figures_dir"] = str(Path(path).parent)
    write_report(results, context, work, results_dir, rel_to=rel_to)
    return file_sha256(work / "report.json"), {"files": sorted(p.name for p in work.iterdir())}


STAGE_CODE = {
    "generate": (("sensors.generate",), generate_stage),
    "train": (("study.engine.train",), train_stage),
    "gatedata": (("study.engine.scoring", "study.eco.data", "study.engine.gate_data"), gatedata_stage),
    "gates": (("study.eco.latency_energy", "study.eco.config_gate_study", "study.engine.gate_training"), gates_stage),
    "crossover": (("study.experiments.crossover",), crossover_stage),
    "transitions": (("study.experiments.transitions",), transitions_stage),
    "evaluate": (("study.pipeline.evaluation",), evaluate_stage),
    "pem": (("study.experiments.pem_section",), pem_stage),
    "report": (("study.report.build",), report_stage),
}
"""Per stage: the modules it runs and its stage function; their code is part of its key."""


def _gates_k(cfg: StudyConfig) -> int:
    """The k HydraFusion's gates are chosen at: `evaluate.k` of the paper run's branches (the whole
    paper set when `train.branches` is empty); 1 where that leaves nothing to rank (k of every branch)."""
    from study.engine.train import branch_set

    k = cfg.evaluate.k
    branches = len(cfg.train.branches) or len(branch_set("paper", cfg.profile))
    return int(k) if isinstance(k, int) and 1 <= k < branches else 1


def stage_identity(name: str, cfg: StudyConfig, setup) -> dict:
    """What stage `name`'s output depends on beyond its config section and its upstream stages:
    its code, its device type and precision, and (generate) the sensor model version and sensor
    profile, (train) the model profile's contents, (report) REPORT_VERSION."""
    from study.engine.code_identity import code_digest
    from study.engine.device import compute_identity

    modules, func = STAGE_CODE[name]
    out = {"code": code_digest(modules, (func,))[:16],
           "compute": compute_identity(device="cpu") if name in ("generate", "report") else compute_identity(setup)}
    if name in ("generate", "crossover", "transitions"):  # these two generate their own sets
        import sensors
        from sensors.rig import load_profile as sensor_profile

        out["sensor_model_version"] = sensors.SENSOR_MODEL_VERSION
        out["sensor_profile"] = json_digest(to_dict(sensor_profile(cfg.profile)))[:16]
    elif name == "train":
        from fusion.nets import load_profile as model_profile

        out["model_profile"] = json_digest(to_dict(model_profile(cfg.profile)))[:16]
        if cfg.train.init_from:  # the weights it starts from, not their name
            out["init_from_sha256"] = file_sha256(Path(_init_from(cfg.train.init_from)) / "checkpoint.pt")[:16]
        from study.pipeline.checks import detectors_run

        for key in ("detectors", "early_detectors"):  # the weights it adopts, not their name
            if getattr(cfg.train, key):
                out[f"{key}_sha256"] = file_sha256(detectors_run(getattr(cfg.train, key), key) / "checkpoint.pt")[:16]
    elif name == "report":
        import study.report.build

        out["report_version"] = study.report.build.REPORT_VERSION
    return out


def run_study(cfg: StudyConfig, out: str | Path, until: str = "report", progress: bool = True) -> dict:
    """Run (or continue) the study in `out` up to stage `until`; returns the stage summary and,
    when the report stage ran or was skipped, the report's JSON (every number of the report)."""
    if until not in STAGES:
        raise UserError(f"--until: unknown stage {until!r} (choose from: {', '.join(STAGES)})")
    from study.pipeline.checks import check_study_config

    check_study_config(cfg)  # the sections against each other, whole, before any folder or stage
    study = Study(cfg, out, progress)
    study.prepare()
    setup = _device_setup(cfg)
    t_start = time.perf_counter()
    last = STAGES.index(until)
    result: dict = {"out": str(study.out)}

    eval_setup = _eval_setup(setup)

    def ident(name: str) -> dict:
        return stage_identity(name, cfg, setup if name == "train" else eval_setup)

    gcfg = cfg.data.generate_config(cfg.profile)
    gen = study.stage("generate", {"data": gcfg.to_dict(), **ident("generate")}, (), generate_stage,
                      gcfg=gcfg, workers=cfg.run.workers, backend=cfg.run.backend, progress=progress)
    data = gen.dir / "data"
    sets = {"detectors": gen}
    for part in cfg.data.parts()[1:]:  # the gate and test sets, each its own dataset and stage
        pcfg = cfg.data.generate_config(cfg.profile, part)
        sets[part] = study.stage(f"{part}set", {"data": pcfg.to_dict(), **ident("generate")}, (), generate_stage,
                                 gcfg=pcfg, workers=cfg.run.workers, backend=cfg.run.backend, progress=progress)
    gate_parts = {p: r.dir / "data" for p, r in sets.items() if p != "test"}
    all_parts = {p: r.dir / "data" for p, r in sets.items()}
    if last < 1:
        return _finish(study, result, t_start)

    train_inputs = {k: v for k, v in to_dict(cfg.train).items()  # unset: the keys as before they existed
                    if v or k not in ("detectors", "early_detectors")}
    tr = study.stage("train", {"profile": cfg.profile, "train": train_inputs, **ident("train")}, (gen,),
                     train_stage, data=data, train_cfg=cfg.train, profile=cfg.profile, setup=setup, say=study.say,
                     progress=progress)
    run_early = tr.dir / "early" if cfg.train.early_fusion else None
    tr_paper = _paper_view(tr, {"profile": cfg.profile, "train": train_inputs, **ident("train")}, gen)
    if last < 2:
        return _finish(study, result, t_start)

    settings = eco_settings(cfg)
    gdr = study.stage("gatedata", {"eco_max_frames": cfg.gates.eco_max_frames, "fusion": cfg.gates.fusion,
                                   "batch_size": cfg.train.batch_size, "val_fraction": cfg.gates.val_fraction,
                                   "seed": cfg.gates.seed, **ident("gatedata")},
                      (tr_paper, *(sets[p] for p in gate_parts if p != "detectors")),
                      gatedata_stage, run_paper=tr.dir / "paper", parts=gate_parts, settings=settings,
                      batch_size=cfg.train.batch_size, setup=eval_setup, progress=progress,
                      val_fraction=cfg.gates.val_fraction, seed=cfg.gates.seed)
    if last < 3:
        return _finish(study, result, t_start)

    gate_data = gdr.dir / "data" if len(gate_parts) > 1 else data
    gates_inputs = {k: v for k, v in to_dict(cfg.gates).items() if v or k != "curve"}  # unset: the keys as before
    gates_k = _gates_k(cfg)
    gt = study.stage("gates", {"gates": gates_inputs, **({"k": gates_k} if gates_k > 1 else {}), **ident("gates")},
                     (gdr,), gates_stage, gatedata_run=gdr.dir / "run", data=gate_data, gates=cfg.gates,
                     settings=settings, setup=eval_setup, say=study.say, progress=progress, k=gates_k)
    if last < STAGES.index("crossover"):
        return _finish(study, result, t_start)

    cx = None
    if cfg.crossover is not None:
        cx = study.stage("crossover", {"crossover": to_dict(cfg.crossover), "profile": cfg.profile,
                                       "batch_size": cfg.train.batch_size, **ident("crossover")}, (tr_paper,),
                         crossover_stage, run_paper=tr.dir / "paper", cfg=cfg, setup=eval_setup, progress=progress)
    if last < STAGES.index("evaluate"):
        return _finish(study, result, t_start)

    evaluate_inputs = {k: v for k, v in to_dict(cfg.evaluate).items()  # the default: the keys as before it existed
                       if not (k == "fusion" and v == "validation") and not (k == "interval" and v == "sequence")}
    ev = study.stage("evaluate", {"evaluate": evaluate_inputs, **ident("evaluate")},
                     (gt, tr, *((sets["test"],) if "test" in sets else ()), *((cx,) if cx else ())),
                     evaluate_stage, gates_run=gt.dir / "run", run_early=run_early, parts=all_parts, cfg=cfg,
                     settings=settings, setup=eval_setup, progress=progress,
                     **({"crossover": cx.dir / "crossover.json"} if cx else {}))
    extra = {}  # the optional stages below the evaluation: {stage: (its record, the file the report reads)}
    if cfg.pem is not None and last >= STAGES.index("pem"):
        pm = study.stage("pem", {**pem_inputs(cfg), **ident("pem")},
                         (tr_paper, *(sets[p] for p in ("gate", "test") if p in sets)), pem_stage,
                         run_paper=tr.dir / "paper", parts=all_parts, cfg=cfg, setup=eval_setup, progress=progress)
        extra["pem"] = (pm, pm.dir / "pem.json")
    if cfg.transitions is not None and last >= STAGES.index("transitions"):
        tx = study.stage("transitions", {**transitions_inputs(cfg), **ident("transitions")}, (gt,),
                         transitions_stage, gates_run=gt.dir / "run", cfg=cfg, setup=eval_setup, progress=progress,
                         gate_data=gate_data)
        extra["transitions"] = (tx, tx.dir / "transitions.json")
    if last < STAGES.index("report"):
        return _finish(study, result, t_start)
    return _report(study, cfg, ev, extra, ident("report"), result, t_start)


def _report(study: Study, cfg: StudyConfig, ev: StageRecord, extra: dict, identity: dict, result: dict,
            t_start: float) -> dict:
    """The report stage (it reads the evaluation and the optional stages in `extra`), its files copied to
    the study's folder."""
    context = {"scale": cfg.scale, "meaningless": cfg.meaningless, "config": to_dict(cfg),
               "stages": {n: r.manifest for n, r in study.records.items()},
               "stage_dirs": {n: str(r.dir) for n, r in study.records.items()}}
    upstream = (ev, *(extra[n][0] for n in ("transitions", "pem") if n in extra))  # (transitions first, as before)
    rp = study.stage("report", {"scale": cfg.scale, "meaningless": cfg.meaningless, **identity}, upstream,
                     report_stage, results_dir=ev.dir, context=context, rel_to=study.out,
                     **{n: path for n, (_, path) in extra.items()})
    for name in ("report.md", "report.html", "report.json"):
        with atomic_path(study.out / name) as tmp:
            shutil.copyfile(rp.dir / name, tmp)
    result["report"] = {n: str(study.out / n) for n in ("report.md", "report.html", "report.json")}
    result["report_json"] = json.loads((study.out / "report.json").read_text())
    return _finish(study, result, t_start)


def _finish(study: Study, result: dict, t_start: float) -> dict:
    result["stages"] = study.summary()
    result["seconds"] = round(time.perf_counter() - t_start, 2)
    ran = [n for n, r in study.records.items() if r.status == "ran"]
    study.say(f"finished in {result['seconds']} s; ran: {', '.join(ran) or 'nothing (every stage was done)'}")
    return result
