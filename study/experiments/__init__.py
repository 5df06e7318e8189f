"""What is measured: each command's or study stage's experiment (compare, outside detectors and gates,
the nuScenes export and metrics, the crossover, the physical gate, transitions, theory, scenes and
galleries) and the study's analyses (bounds, regrets, the energy front, coverage, replication)."""
