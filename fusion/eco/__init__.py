"""EcoFusion (Malawade, Mortlock, Al Faruque, DAC 2022): energy-aware configuration selection.

A *configuration* is a non-empty set of HydraFusion branches, executed and late-fused
(EcoFusion Section 4, Algorithm 1). This package holds the library side:

- `configurations`: the configuration set Phi (every non-empty subset by default, the paper's
  named baselines marked), loaded strictly from YAML.
- `loss`: the fused loss L_f(phi) of one frame's fused detections (Section 3.3, defined here
  explicitly because fused boxes carry no logits or proposals).
- `optimise`: candidates Phi* (Eq. 7, as written and as the prose states it), L_joint (Eq. 8),
  the argmin (Eq. 9), energy normalisation.
- `energy`: E = P t (Eq. 6) with t from measured stem / branch / fusion latencies and P from a
  counter (NVML, RAPL) where one exists, else a stated model (PX2 45.4 W preset); sensor clock
  gating (Section 5.5.2, Eq. 10-11).
- `gates`: configuration gates (knowledge, deep, attention, loss-based) and `EcoFusionSelector`,
  which wires the joint optimisation into `HydraFusion.gate` so only the chosen branches run.
"""
