"""The staged study (`hydrabench study`): its config and presets, the checks before work, the stages,
their cache (`cache`: keys, partial directories, manifests) and the evaluation stage (`evaluation`)."""
