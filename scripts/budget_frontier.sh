#!/usr/bin/env bash
# Where the single-sensor aims of issue 27 would be reached: the budget frontier of the lidar and the
# right-camera branch (`hydrabench bench recipe` with candidates that differ only in their number of
# epochs, each a whole schedule with its learning-rate drop at 3/4), at the reference model's width
# (0.5) with the recipe bench's choice (64 sampled RoIs), every epoch scored on the gate split (held
# out), then the longest schedule of each measured on the test split (`evaluate`, 500 draws): lidar
# and camera under `reference`, the camera also under `visible` in the clear contexts (its 0-15 m aim).
#
#   scripts/budget_frontier.sh DATA WORK [EPOCHS...]
#
# DATA: the `cpu` study's dataset (`hydrabench study cpu --out X --until generate`, then
# X/stages/generate-*/data); WORK: a scratch directory (resumable: rerun after an interruption);
# EPOCHS: the schedules (default 6 12 24). About 85 min on 2 AVX512-BF16 EPYC cores.
set -euo pipefail
DATA=${1:?usage: $0 DATA WORK [EPOCHS...]}
WORK=${2:?usage: $0 DATA WORK [EPOCHS...]}
shift 2
[ $# -gt 0 ] || set -- 6 12 24
EPOCHS=("$@")
H=${HYDRABENCH:-hydrabench}
mkdir -p "$WORK"
for spec in "lidar 0.35" "camera_right 0.20"; do
  read -r branch aim <<< "$spec"
  cands=()
  for e in "${EPOCHS[@]}"; do cands+=(--candidate "$e epochs:epochs=$e+model=box_batch_size_per_image=64"); done
  $H bench recipe "$DATA" --out "$WORK/$branch" --branch "$branch" --aim "$aim" "${cands[@]}" --bootstrap 500 \
    --plot "$WORK/$branch.png" --json > "$WORK/$branch.json"
  longest="$WORK/$branch/${EPOCHS[-1]}_epochs"
  $H evaluate "$longest" "$DATA" --branches "$branch" --bootstrap 500 --json > "$WORK/${branch}_test_reference.json"
done
$H evaluate "$WORK/camera_right/${EPOCHS[-1]}_epochs" "$DATA" --branches camera_right --protocol visible \
  --contexts city,junction,motorway,rural --bootstrap 500 --json > "$WORK/camera_right_test_visible.json"
