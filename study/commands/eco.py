"""The EcoFusion commands (eco-data, eco-energy, eco-train-gate, eco-evaluate, eco-sweep): the command
lines of `study.eco` (what each computes is described there) and their text."""

from __future__ import annotations

import argparse
from pathlib import Path

from sim.errors import UserError
from study import eco
from study.cli import (
    FUSION_HELP,
    Formatter,
    bootstrap_int,
    checkpoint_arg,
    dataset_dir,
    emit,
    float_range,
    fusion_arg,
    holdout_fraction,
    in_file,
    name_arg,
    name_list,
    nonneg_float,
    nonneg_int,
    out_dir,
    pool_grid,
    pos_float,
    pos_int,
    training_run,
)
from study.commands.train_gate import add_objective_args, format_choice_lines, parse_objective_fields
from study.eco.config_gate_study import train_eco_gate
from study.eco.data import EcoSettings, build_eco_data
from study.eco.ecofusion_eval import GATE_ORDER, EcoEval, evaluate_eco, execute_ecofusion
from study.eco.latency_energy import energy_table
from study.eco.sweep import SWEEP_LAMBDAS, sweep
from study.engine.gate_training import GateTrainConfig

EPILOG = """\
examples:
  hydrabench eco-data runs/all7 data/train1600 --json
  hydrabench eco-energy runs/all7 data/train1600 --threads 1 --json
  hydrabench eco-train-gate runs/all7 data/train1600 --gate attention
  hydrabench eco-evaluate runs/all7 data/train1600 --lambda-e 0.01 --gamma 0.5 --json
  hydrabench eco-sweep runs/all7 data/train1600 --out out/eco --json
DATA must be the run's training dataset: gates train on its train split and every table is on its
test split. Commands share the configuration dataset, the gates and the latency table in RUN.
"""


def _common(p, energy: bool = True) -> None:
    p.add_argument("run_dir", metavar="RUN", type=training_run, help="training run directory (hydrabench train --out)")
    p.add_argument("data", type=dataset_dir, help="the run's training dataset")
    p.add_argument("--configurations", type=_configurations_file, default=None, help="YAML file of the configuration set (keys: subsets all|listed, "
                   "max_branches, configurations, baselines); default: every non-empty subset of the branches")
    p.add_argument("--fusion", default="wbf", type=fusion_arg,
                   help=f"late fusion of a configuration's branches (EcoFusion 4.4: WBF): {FUSION_HELP}")
    p.add_argument("--checkpoint", type=checkpoint_arg, default="latest", help="latest, or epoch-NNN")
    p.add_argument("--batch-size", type=pos_int, default=4, help="frames per forward when building the dataset")
    p.add_argument("--max-frames", type=nonneg_int, default=0, help="use at most this many frames of each split "
                   "(evenly spaced; 0 = all): for slow machines")
    p.add_argument("--fp-weight", type=_fp_weight, default=1.0,
                   help="weight of L_f's false-positive term (fusion.eco.loss): what the learned gates regress and "
                   "the Loss-based oracle minimises. Lower it to let the gates choose fusion, which adds "
                   "low-score boxes that AP tolerates but the false-positive term charges. The cached "
                   "configuration dataset is reused; gates trained at another weight live in "
                   "RUN/eco/gates/<gate>-fp<w>/ (default: 1, EcoFusion's loss as defined here)")
    if energy:
        p.add_argument("--power", type=_power, default="px2", help="P of Eq. 6 where no energy counter exists: px2 (45.4 W, the "
                       "paper's Drive PX2 under load) or watts")
        p.add_argument("--energy-scale", default="px2", choices=["px2", "late", "joules"],
                       help="what lambda_E weighs: px2 = E / E(late) x 3.798 J (PX2-equivalent joules), late = "
                       "E / E(late), joules = this machine's J (machine-dependent lambda_E)")
        p.add_argument("--loss-scale", default="late", choices=["late", "raw"],
                       help="the L_f that lambda_E and gamma weigh: late = L_f / late fusion's mean training L_f "
                       "(late fusion at 1, as on the paper's scale; gamma a share of it), raw = L_f as computed")
        p.add_argument("--rule", default="prose", choices=["prose", "equation"],
                       help="Eq. 7 candidates: prose = within gamma of the best loss; equation = as printed, "
                       "L - L* <= L* + gamma")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")


_fp_weight = float_range(0.0, 100.0, "fp_weight")


def _settings(args) -> EcoSettings:
    return EcoSettings(configurations=args.configurations or "", fusion=args.fusion, checkpoint=args.checkpoint,
                       power=getattr(args, "power", "px2"), energy_scale=getattr(args, "energy_scale", "px2"),
                       loss_scale=getattr(args, "loss_scale", "late"),
                       rule=getattr(args, "rule", "prose"), batch_size=args.batch_size, max_frames=args.max_frames,
                       fp_weight=args.fp_weight)


def _unit(text: str, name: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"{name} must be in [0, 1], got {v}")
    return v


def _lambda(text: str) -> float:
    return _unit(text, "lambda_E")


def _configurations_file(text: str) -> str:
    """An argparse type: a configuration-set YAML file that reads (strict keys, valid values)."""
    from fusion.eco.configurations import load_configurations_config

    path = in_file(text)
    try:
        load_configurations_config(path)
    except (UserError, ValueError, TypeError) as exc:
        raise argparse.ArgumentTypeError(f"{path}: {exc}") from None
    return path


_configurations_file.kind = "in_file"


def _gate_list(text: str) -> str:
    """An argparse type: a comma-separated list of configuration gates (GATE_ORDER)."""
    for g in name_list(text):
        if g not in GATE_ORDER:
            raise argparse.ArgumentTypeError(f"unknown gate {g!r} (choose from: {', '.join(GATE_ORDER)})")
    return text


_gate_list.kind = "names"


def _lambda_list(text: str) -> str:
    """An argparse type: a comma-separated list of lambda_E values in [0, 1]."""
    for t in name_list(text):
        _lambda(t)
    return text


_lambda_list.kind = "names"


def _power(text: str) -> str:
    """An argparse type: 'px2' or a machine power in watts (> 0, finite)."""
    from fusion.eco.energy import power_model

    text = str(text).strip()
    try:
        power_model(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


_power.kind = "name"


def _require_trained(run_dir, gates, s: EcoSettings) -> None:
    """Before any work: every learned gate asked for has been trained for these settings' L_f
    (`EcoSettings.gate_dir`/gate.pt)."""
    from fusion.eco.config_gates import CONFIG_GATES
    from fusion.nets.branch_gates import trainable_gates

    fp = s.fp_flag()
    learned = trainable_gates(CONFIG_GATES)
    for g in gates:
        if g in learned and not (s.gate_dir(run_dir, g) / "gate.pt").exists():
            raise UserError(f"no trained {g} configuration gate in {run_dir}{' for' + fp if fp else ''} (run: "
                            f"hydrabench eco-train-gate {run_dir} DATA --gate {g}{fp}, or leave it out of --gates)")


SWEEP_FILES = ("figure4_loss_energy.png", "figure5_scenes.png", "result.json")


def _check_sweep_out(out: Path) -> None:
    """An eco-sweep --out holds nothing but an earlier sweep's files (they are replaced)."""
    if out.is_dir():
        foreign = sorted(p.name for p in out.iterdir() if p.name not in SWEEP_FILES)
        if foreign:
            raise UserError(f"--out {out} holds files that are not an eco-sweep's ({foreign[0]}); use a new or "
                            "empty directory")


def _gates(text: str) -> list[str]:
    names = [g.strip() for g in text.split(",") if g.strip()] if text else list(GATE_ORDER)
    bad = [g for g in names if g not in GATE_ORDER]
    if bad:
        raise UserError(f"--gates: unknown gate {bad[0]!r} (choose from: {', '.join(GATE_ORDER)})")
    return names


def add_eco_data(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=eco.__doc__.split("**Latency")[0], epilog=EPILOG,
                       formatter_class=Formatter)
    _common(p, energy=False)
    p.set_defaults(run=run_eco_data)


def run_eco_data(args) -> int:
    r = build_eco_data(Path(args.run_dir), Path(args.data), _settings(args))

    def text(r):
        lines = [f"{r['configurations']} configurations, {r['frames']['train']} train / {r['frames']['test']} test frames "
                 f"({r['computed_frames']} computed now, {r['seconds']} s); cache {r['eco_data']}",
                 f"L_f vs per-frame AP@0.5 on the {r['loss_vs_ap_on']} (rank correlation across configurations, "
                 "mean over frames):"]
        for k, v in r["loss_vs_ap_validation"].items():
            lines.append(f"  {k:24s} Spearman {v['spearman_mean']}  Kendall {v['kendall_mean']}  lowest loss has the best "
                         f"AP in {v['lowest_loss_has_best_ap']} of {v['frames']} frames")
        lines.append(f"mean L_f per configuration on the test split (fp weight {r['loss_definition']['fp_weight']:g}): "
                     + ", ".join(f"{k} {v}" for k, v in r["mean_loss_test"].items())
                     + f"; lowest: {r['lowest_mean_loss_test']}")
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0


def add_eco_energy(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=eco.__doc__.split("**Latency and energy**")[1].split("**Gates**")[0],
                       epilog=EPILOG, formatter_class=Formatter)
    _common(p)
    p.add_argument("--threads", type=pos_int, default=1, help="torch CPU threads while timing")
    p.add_argument("--repeats", type=pos_int, default=3, help="timed runs per component and frame (median)")
    p.add_argument("--frames", type=pos_int, default=3, help="test frames timed")
    p.add_argument("--counter", default="auto", choices=["auto", "rapl", "nvml", "none"],
                   help="energy counter: auto uses RAPL / NVML where readable, else the --power model")
    p.add_argument("--check", type=pos_int, default=12, help="configurations timed end to end to check the additive "
                   "model: late fusion, all branches, the other baselines, then random ones")
    p.add_argument("--fresh", action="store_true", help="measure again even when RUN/eco/latency.json matches")
    p.set_defaults(run=run_eco_energy)


def run_eco_energy(args) -> int:
    s = _settings(args)
    try:
        r = energy_table(Path(args.run_dir), Path(args.data), s, threads=args.threads, repeats=args.repeats,
                         frames=args.frames, counter=args.counter, fresh=args.fresh, n_check=args.check)
    except OSError as exc:
        raise UserError(str(exc)) from None
    for k in ("_model", "_t", "_e"):
        r.pop(k)

    def text(r):
        lm = r["latency_model"]
        lines = ["stems [ms]: " + ", ".join(f"{k} {v}" for k, v in lm["stems_ms"].items()),
                 "branches [ms]: " + ", ".join(f"{k} {v}" for k, v in lm["branches_ms"].items()),
                 "fusion block [ms] by branches fused: " + ", ".join(f"{k}: {v}" for k, v in lm["fusion_ms"].items()),
                 f"additive model vs timed end to end: mean |error| {r['additive_check']['mean_abs_relative_error']}, "
                 f"max {r['additive_check']['max_abs_relative_error']}",
                 f"energy: {r['energy_source']}"]
        for k, v in r["baselines"].items():
            lines.append(f"  {k:18s} {v['configuration']:40s} {v['latency_ms']:9.2f} ms {v['energy_j']:9.4f} J")
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0


def add_eco_train_gate(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=eco.__doc__.split("**Gates**")[1].split("**Evaluation**")[0],
                       epilog=EPILOG, formatter_class=Formatter)
    _common(p, energy=False)
    p.add_argument("--gate", required=True, type=name_arg, help="deep | attention")
    p.add_argument("--epochs", type=pos_int, default=100, help="passes over the training frames (more: continues)")
    p.add_argument("--gate-batch-size", type=pos_int, default=32, help="frames per Adam step")
    p.add_argument("--lr", type=pos_float, default=5e-5, help="Adam learning rate (HydraFusion 5.3's gate rate)")
    p.add_argument("--val-fraction", type=holdout_fraction, default=0.15, help="share of the gate split's sequences (the train split's when the run has none) held out to pick the epoch")
    p.add_argument("--grid", type=pool_grid, default="8x16", help="ROWSxCOLS the stem features are pooled to")
    p.add_argument("--seed", type=nonneg_int, default=0, help="initialisation, data order, validation split")
    p.add_argument("--threads", type=pos_int, default=2, help="torch CPU threads")
    add_objective_args(p)
    p.add_argument("--fresh", action="store_true", help="discard a previous training of this gate")
    p.set_defaults(run=run_eco_train_gate)


def run_eco_train_gate(args) -> int:
    if not args.lr > 0:
        raise UserError(f"--lr must be > 0, got {args.lr}")
    cfg = GateTrainConfig(gate=args.gate, epochs=args.epochs, batch_size=args.gate_batch_size, lr=args.lr,
                          val_fraction=args.val_fraction, seed=args.seed, grid=tuple(args.grid),
                          checkpoint=args.checkpoint, threads=args.threads, **parse_objective_fields(args))
    r = train_eco_gate(Path(args.run_dir), Path(args.data), args.gate, cfg, _settings(args), fresh=args.fresh)

    def text(r):
        return "\n".join([
            f"{r['gate']} configuration gate ({r['configurations']} outputs): held-out MAE {r['test_mae']} vs constant "
            f"{r['constant_mean_mae']} on {r['test_frames']} test frames (best epoch {r['best_epoch']} of {r['epochs']})",
            f"  mean L_f of its lowest-predicted configuration {r['test_loss_of_predicted_best']}, of the best "
            f"constant configuration {r['test_loss_of_constant_best']}, oracle {r['test_loss_of_oracle_best']}",
            *format_choice_lines(r, "L_f of the chosen configuration"),
            f"  saved {r['gate_path']}"])

    emit(r, args.json, text)
    return 0


def add_eco_evaluate(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=eco.__doc__.split("**Evaluation**")[1], epilog=EPILOG,
                       formatter_class=Formatter)
    _common(p)
    p.add_argument("--lambda-e", type=_lambda, default=0.01, help="Eq. 8 energy weight lambda_E in [0, 1]")
    p.add_argument("--gamma", type=nonneg_float, default=0.5, help="Eq. 7 loss tolerance gamma (Section 5: 0.5)")
    p.add_argument("--gates", type=_gate_list, default=None, help="comma-separated: knowledge, deep, attention, loss_based (default all; "
                   "deep and attention must be trained with eco-train-gate)")
    p.add_argument("--execute", default="", choices=list(GATE_ORDER), help="also run this gate wired into the network (only the chosen "
                   "branches and their stems run): stem / branch calls per frame, measured latency")
    p.add_argument("--execute-frames", type=nonneg_int, default=0, help="frames for --execute (0 = the test split)")
    p.add_argument("--bootstrap", type=bootstrap_int, default=0, metavar="N",
                   help="95%% intervals of every mAP and of every paired difference (each gate minus late fusion "
                   "above all), overall and per context, from N draws of whole sequences, every configuration "
                   "scored on the same draw (default: 0, none; 1000 for a table)")
    p.set_defaults(run=run_eco_evaluate)


def run_eco_evaluate(args) -> int:
    s = _settings(args)
    gates = _gates(args.gates)
    if args.execute and args.execute not in GATE_ORDER:
        raise UserError(f"--execute: unknown gate {args.execute!r} (choose from: {', '.join(GATE_ORDER)})")
    if args.execute and args.execute not in gates:
        gates.append(args.execute)
    _require_trained(args.run_dir, gates, s)
    ev = EcoEval(Path(args.run_dir), Path(args.data), s, gates)
    r = evaluate_eco(args.run_dir, args.data, args.lambda_e, args.gamma, s, gates, ev=ev, bootstrap=args.bootstrap)
    if args.execute:
        r["executed"] = execute_ecofusion(Path(args.run_dir), Path(args.data), args.execute, args.lambda_e, args.gamma,
                                          s, args.execute_frames, ev=ev)

    def text(r):
        lines = [f"lambda_E {r['lambda_e']}, gamma {r['gamma']} ({r['rule']} rule), {r['frames']} test frames, "
                 f"{r['configurations']} configurations; energy in {r['energy_unit']}",
                 f"{'':22s} {'mAP':>7s} {'avg L_f':>8s} {'energy':>8s} {'latency ms':>10s}"]
        for k, v in list(r["baselines"].items()) + [(f"EcoFusion {g}", v) for g, v in r["gates"].items()]:
            lines.append(f"{k:22s} {v['map'] if v['map'] is not None else '-':>7} {v['avg_loss']:8.4f} "
                         f"{v['energy']:8.4f} {v['latency_ms']:10.2f}")
        for g, v in r["against_late"].items():
            band = v.get("map_minus_late_ci95")
            lines.append(f"  {g} vs late: mAP {v['map_minus_late']}"
                         + (f" [{band[0]}, {band[1]}] (95%, {r['ci95']['resamples']} sequence draws)" if band else "")
                         + f", energy x{v['energy_ratio']}, latency x{v['latency_ratio']}")
        if "executed" in r:
            x = r["executed"]
            lines.append(f"executed {x['gate']}: stems per frame {x['stem_runs_per_frame']}, branches per frame "
                         f"{x['branch_runs_per_frame']}, {x['measured_latency_ms']} ms per frame measured "
                         f"({x['additive_latency_ms']} additive)")
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0


def add_eco_sweep(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=eco.__doc__.split("**Evaluation**")[1], epilog=EPILOG,
                       formatter_class=Formatter)
    _common(p)
    p.add_argument("--out", required=True, type=out_dir, help="directory for figure4_loss_energy.png, figure5_scenes.png, result.json")
    p.add_argument("--gamma", type=nonneg_float, default=0.5, help="Eq. 7 loss tolerance gamma (Section 5: 0.5)")
    p.add_argument("--lambdas", type=_lambda_list, default=",".join(f"{x:g}" for x in SWEEP_LAMBDAS),
                   help="comma-separated lambda_E values of Figure 4 (Tables 1-2's values are always added)")
    p.add_argument("--gates", type=_gate_list, default=None, help="comma-separated gates (default all four)")
    p.add_argument("--figure-gate", default="", choices=list(GATE_ORDER), help="the EcoFusion gate of Table 1 and Figure 5 (default: attention "
                   "when evaluated, else the first of --gates)")
    p.set_defaults(run=run_eco_sweep)


def run_eco_sweep(args) -> int:
    from study.outputs import check_writable_dir

    s = _settings(args)
    try:
        lambdas = [_lambda(t) for t in args.lambdas.split(",") if t.strip()]
    except argparse.ArgumentTypeError as exc:
        raise UserError(f"--lambdas: {exc}") from None
    gates = _gates(args.gates)
    fig_gate = args.figure_gate or ("attention" if "attention" in gates else gates[0])
    if fig_gate not in gates:
        raise UserError(f"--figure-gate {fig_gate!r} is not among the evaluated gates ({', '.join(gates)})")
    _require_trained(args.run_dir, gates, s)
    out = check_writable_dir(args.out)
    _check_sweep_out(out)
    r = sweep(Path(args.run_dir), Path(args.data), out, args.gamma, lambdas, s, gates, fig_gate)

    def text(r):
        lines = [f"Table 1 ({r['frames']} test frames; energy in {r['energy_unit']})",
                 f"{'':36s} {'mAP':>7s} {'energy':>8s} {'latency ms':>10s}"]
        for k, v in r["table1"].items():
            lines.append(f"{k:36s} {v['map'] if v['map'] is not None else '-':>7} {v['energy']:8.4f} "
                         f"{v['latency_ms']:10.2f}")
        lines.append("Table 2: lambda_E x gate: mAP / avg L_f / energy")
        for lam, row in r["table2"].items():
            for g, v in row.items():
                lines.append(f"  {lam:>5s} {g:11s} {v['map']} / {v['avg_loss']} / {v['energy']}")
        lines.append("Table 3: sensor + compute energy per scene (clock gating)")
        for k, row in r["table3"].items():
            lines.append(f"  {k:32s} " + ", ".join(f"{c} {v}" for c, v in row.items()))
        lines.append("figures: " + ", ".join(r["figures"]))
        return "\n".join(lines)

    emit(r, args.json, text)
    return 0
