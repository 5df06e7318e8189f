"""EcoFusion on a trained run (EcoFusion, DAC 2022): the configuration dataset, the configuration
gates, measured latency and energy, the joint optimisation, and Tables 1-3 / Figures 4-5.

**Configuration dataset** (`EcoData`, the gate dataset of `study.engine.gate_data.GateData` with more per-frame
arrays): for every frame, the pooled stem features (what the learned gates read), each branch's
detections (every branch runs once per frame, in its own frame), and for every configuration phi
of the set Phi (`fusion.eco.configurations`) the parts of the fused loss L_f(phi)
(`fusion.eco.loss`) and the frame's VOC AP@0.5 of the fused detections. Subsets are fused
afterwards from the branches' detections: a branch's output depends only on its own sensors'
stem features, never on which other branches run, so this equals executing each configuration
(tested). Cached under `RUN/eco_data/<key>/` (key: checkpoint, dataset, configurations, fusion
method, loss definition), written in chunks atomically; interrupted, it continues.

**Latency and energy** (`measure_latency`, Eq. 6): each stem, branch and the fusion block are
timed on real frames at batch 1; a configuration's latency is the sum of its stems (each once),
its branches and the fusion block; that sum is checked against configurations timed end to end.
Energy is measured where a counter exists (RAPL on a CPU, NVML on an NVIDIA GPU), else modelled as
P x t with a stated P (the PX2's 45.4 W by default). Cached in `RUN/eco/latency.json` per machine,
thread count and checkpoint.

**Gates** (`train_eco_gate`): the deep and attention configuration gates regress L_f of every
configuration from the pooled stem features, with mean absolute error and Adam at lr 5e-5 on the
run's train split (`study.engine.gate_training.fit_gate`), saved in `RUN/eco/gates/<gate>/`.

**Evaluation** (`evaluate_eco`, `sweep`): on the run's test split, each gate's predictions go
through the joint optimisation (Eq. 7-9, `fusion.eco.optimise`) at lambda_E and gamma; the chosen
configuration of each frame is fused and scored: mAP@0.5 (right camera, difficult boxes ignored),
mean actual L_f, mean energy and latency of the chosen configurations, sensor energy with clock
gating (Eq. 10-11) per scene.
"""

# Where each part lives:
#   study.eco.data               EcoData, EcoSettings, build_eco_data, rank_correlation   (configuration dataset)
#   study.eco.latency_energy     measure_latency, energy_table                            (latency and energy)
#   study.eco.config_gate_study  train_eco_gate, load_eco_gate                            (gates)
#   study.eco.ecofusion_eval     EcoEval, evaluate_eco, execute_ecofusion                 (evaluation)
#   study.eco.sweep              sweep, plot_figure4, plot_figure5                        (Tables 1-3, Figures 4-5)
