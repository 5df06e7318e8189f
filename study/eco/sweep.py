"""EcoFusion Tables 1-3 and Figures 4-5 over a lambda_E sweep (`sweep`, `hydrabench eco-sweep`).
See `study.eco`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.progress import progress as progress_bar
from study.eco.data import EcoSettings
from study.eco.ecofusion_eval import METRIC, EcoEval
from study.outputs import write_json_atomic

TABLE1_LAMBDAS = (0.0, 0.01, 0.05)
TABLE2_LAMBDAS = (0.0, 0.01, 0.1)
SWEEP_LAMBDAS = (0.0, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0)
FIG5_BASELINES = ("none_radar", "early", "late")


def clock_gating_table(sources, suffix: str) -> dict:
    """EcoFusion Table 3: sensor + compute energy per scene, late fusion with every sensor measuring,
    the gates clock-gating what they do not use, and each gate's savings against late fusion in %.
    `sources`: (label, metrics with per_scene); `suffix`: "" (per fused frame) or "_per_measurement"."""
    table = {}
    for label, src in sources:
        key = ("energy_all_sensors_on" if label == "late_fusion" else "energy_clock_gated") + suffix
        table[label] = {ctx: v[key] for ctx, v in src["per_scene"].items()}
        table[label]["overall"] = src[key]
    for label in [k for k in table if k != "late_fusion"]:
        table[f"{label}_savings_pct"] = {ctx: round(100 * (1 - table[label][ctx] / table["late_fusion"][ctx]), 2)
                                         for ctx in table[label]}
    return table


def sweep(run_dir, data, out: Path, gamma: float = 0.5, lambdas=SWEEP_LAMBDAS, s: EcoSettings = EcoSettings(),
          gates=None, fig_gate: str = "attention", progress: bool = True, ev: EcoEval | None = None) -> dict:
    """`hydrabench eco-sweep`: Tables 1-3 and Figures 4-5 (see README). `ev`: an `EcoEval` of the
    same run, data and settings already loaded (the study's evaluation reuses it)."""
    from fusion.eco.energy import FRAME_HZ, SENSOR_DEVICES, sensor_energy
    from fusion.eco.optimise import pareto_front

    ev = ev or EcoEval(run_dir, data, s, gates, progress=progress)
    gates = list(ev.predicted)
    eco_gate = fig_gate if fig_gate in gates else gates[0]
    lambdas = sorted(set(lambdas) | set(TABLE1_LAMBDAS) | set(TABLE2_LAMBDAS))
    curve = {g: {} for g in gates}
    bar = progress_bar(total=len(gates) * len(lambdas), desc="sweep", enabled=progress)
    for g in gates:
        for lam in lambdas:
            ch = ev.choose(g, lam, gamma)
            curve[g][lam] = {**ev.metrics(ch, per_scene=(lam == 0.01), gate=g), "selected": ev.selection_counts(ch, 3)}
            bar.update(1)
    bar.close()
    base = {name: {**ev.metrics(ev.fixed(name), per_scene=True), "configuration": ev.configs.names[i]}
            for name, i in ev.configs.baselines.items()}
    table1 = {name: {k: base[name][k] for k in ("configuration", "map", "energy", "energy_j", "latency_ms")}
              for name in base}
    for lam in TABLE1_LAMBDAS:
        table1[f"ecofusion_{eco_gate}_lambda_{lam:g}"] = {k: curve[eco_gate][lam][k]
                                                         for k in ("map", "energy", "energy_j", "latency_ms")}
    table2 = {f"{lam:g}": {g: {k: curve[g][lam][k] for k in ("map", "avg_loss", "energy")} for g in gates}
              for lam in TABLE2_LAMBDAS}
    # Table 3: sensors clock-gated per scene, knowledge gate (the paper's choice: external context) and
    # the figure's gate at lambda_E 0.01, against late fusion with every sensor measuring
    late = base.get("late")
    sources = (("late_fusion", late), *((f"ecofusion_{g}", curve[g][0.01]) for g in
                                        dict.fromkeys(("knowledge", eco_gate)) if g in curve)) if late else ()
    table3 = clock_gating_table(sources, "")  # each sensor over one 4 Hz fused frame (the paper's Table 3)
    table3_per_measurement = clock_gating_table(sources, "_per_measurement")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fig4 = out / "figure4_loss_energy.png"
    fig5 = out / "figure5_scenes.png"
    fronts = {g: [lambdas[i] for i in pareto_front([curve[g][lam]["avg_loss"] for lam in lambdas],
                                                  [curve[g][lam]["energy"] for lam in lambdas])] for g in gates}
    plot_figure4(curve, lambdas, fronts, base, fig4, ev.energy_label())
    scenes = {name: base[name]["per_scene"] for name in FIG5_BASELINES if name in base}
    scenes[f"ecofusion_{eco_gate}"] = curve[eco_gate][0.01]["per_scene"]
    plot_figure5(scenes, fig5, ev.energy_label())
    result = {
        "table1": table1, "table2": table2, "table3": table3, "table3_per_measurement": table3_per_measurement,
        "table3_period": f"each sensor over one fused frame at {FRAME_HZ:g} Hz (EcoFusion Table 3); "
                         "table3_per_measurement: over one measurement at the sensor's own rate",
        "table3_sensor_model": {k: {"power_w": d.power_w, "motor_w": d.motor_w, "rate_hz": d.rate_hz,
                                    "energy_measuring_j": round(sensor_energy(d, True, FRAME_HZ), 4),
                                    "energy_clock_gated_j": round(sensor_energy(d, False, FRAME_HZ), 4),
                                    "energy_per_measurement_j": round(sensor_energy(d, True), 4), "source": d.source}
                                for k, d in SENSOR_DEVICES.items()},
        "figure4": {g: {f"{lam:g}": {k: curve[g][lam][k] for k in ("avg_loss", "energy", "energy_configuration", "map")}
                        for lam in lambdas}
                    for g in gates},
        "pareto_lambdas": {g: [f"{x:g}" for x in v] for g, v in fronts.items()},
        "curve": {g: {f"{lam:g}": {k: v for k, v in curve[g][lam].items() if k != "per_scene"} for lam in lambdas}
                  for g in gates},
        "figures": [str(fig4), str(fig5)], "gamma": gamma, "rule": s.rule, "fp_weight": s.fp_weight, "figure_gate": eco_gate,
        "energy_unit": ev.energy_label(), "loss_unit": ev.loss_label(), "additive_check": ev.energy_info["additive_check"],
        "frames": len(ev.test), "configurations": len(ev.configs), "metric": METRIC,
        "run": str(run_dir), "data": str(data),
    }
    write_json_atomic(out / "result.json", result)
    return result


def plot_figure4(curve, lambdas, fronts, base, path: Path, energy_label: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    from study.outputs import savefig_atomic

    gates = list(curve)
    fig, axes = plt.subplots(1, len(gates), figsize=(4.2 * len(gates), 4.0), sharex=True, sharey=True, squeeze=False)
    norm = LogNorm(vmin=min(x for x in lambdas if x > 0), vmax=max(lambdas))
    sc = None
    for ax, g in zip(axes[0], gates):
        e = [curve[g][lam]["energy"] for lam in lambdas]
        lo = [curve[g][lam]["avg_loss"] for lam in lambdas]
        col = [max(lam, norm.vmin) for lam in lambdas]
        sc = ax.scatter(e, lo, c=col, cmap="viridis", norm=norm, s=40, zorder=3, edgecolors="k", linewidths=0.4)
        fe = [curve[g][lam]["energy"] for lam in fronts[g]]
        fl = [curve[g][lam]["avg_loss"] for lam in fronts[g]]
        ax.step(fe, fl, where="post", color="crimson", lw=1.2, zorder=2, label="Pareto front")
        for name, marker in (("late", "s"), ("early", "^"), ("none_radar", "v"), ("none_camera_right", "o")):
            if name in base:
                ax.scatter(base[name]["energy"], base[name]["avg_loss"], marker=marker, facecolors="none",
                           edgecolors="gray", s=50, label=name, zorder=1)
        ax.set_title(g)
        ax.set_xlabel(f"mean energy [{energy_label.split(';')[0].split(':')[0]}]")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("mean fused loss L_f (test frames)")
    axes[0][0].legend(fontsize=7, loc="best")
    cb = fig.colorbar(sc, ax=axes[0].tolist(), shrink=0.9)
    cb.set_label("lambda_E (0 drawn at the lowest value)")
    fig.suptitle("EcoFusion Figure 4 analogue: loss against energy per gate, lambda_E colour-coded", fontsize=10)
    savefig_atomic(fig, path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_figure5(scenes: dict, path: Path, energy_label: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from study.outputs import savefig_atomic

    methods = list(scenes)
    ctxs = sorted({c for v in scenes.values() for c in v})
    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    w = 0.8 / len(methods)
    x = np.arange(len(ctxs))
    for k, m in enumerate(methods):
        axes[0].bar(x + k * w, [scenes[m].get(c, {}).get("avg_loss", np.nan) for c in ctxs], w, label=m)
        axes[1].bar(x + k * w, [scenes[m].get(c, {}).get("energy", np.nan) for c in ctxs], w, label=m)
    axes[0].set_ylabel("mean fused loss L_f")
    axes[1].set_ylabel(f"mean energy\n[{energy_label.split(';')[0].split(':')[0]}]")
    axes[1].set_xticks(x + w * (len(methods) - 1) / 2, ctxs)
    axes[0].legend(fontsize=8, ncol=len(methods))
    for ax in axes:
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle("EcoFusion Figure 5 analogue: loss and energy per scene (test frames)", fontsize=10)
    savefig_atomic(fig, path, dpi=110, bbox_inches="tight")
    plt.close(fig)
