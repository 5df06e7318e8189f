#!/bin/bash
# The learned gates' optional inputs (--pooling global, --context-inputs, both) on a finished study:
#   scripts/gate_inputs.sh STUDY_DIR OUT_DIR
# trains each variant with train-gate / eco-train-gate (--objective auto, the study's --val-fraction 0.5)
# on a link farm of the study's gates stage (the study's own files are never written), one JSON per
# variant in OUT_DIR. docs/results.md "Gate inputs, measured" and results/cpu_study_gate_inputs.json.
set -euo pipefail
study=${1:?usage: scripts/gate_inputs.sh STUDY_DIR OUT_DIR}
out=${2:?usage: scripts/gate_inputs.sh STUDY_DIR OUT_DIR}
hb=${HYDRABENCH:-.venv/bin/hydrabench}
py=${PYTHON:-.venv/bin/python}
gates=$(ls -td "$study"/stages/gates-*/ | while read -r d; do [ -f "$d/manifest.json" ] && echo "$d"; done | head -1)
data=$(ls -d "$study"/stages/generate-*/data | head -1)
[ -n "$gates" ] || { echo "no finished gates stage in $study" >&2; exit 2; }
mkdir -p "$out"
"$py" -c "from study.pipeline.cache import link_farm; link_farm('${gates}run', '$out/run')"
for cmd in train-gate eco-train-gate; do
  for gate in deep attention; do
    for variant in "--pooling global" "--context-inputs" "--pooling global --context-inputs"; do
      [ "$gate" = attention ] && [[ "$variant" == *global* ]] && continue
      name="$cmd-$gate-$(echo "$variant" | tr -d ' -')"
      echo "== $name" >&2
      "$hb" "$cmd" "$out/run" "$data" --gate "$gate" --val-fraction 0.5 --fresh $variant --json > "$out/$name.json"
    done
  done
done
