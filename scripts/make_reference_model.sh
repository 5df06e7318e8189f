#!/usr/bin/env bash
# Make the reference model models/cpu-ref (study.engine.reference_model) from the `cpu` study's dataset:
# the study's four detectors at half width (layer2-4 channels x 0.5, so the float16 weights fit
# issue 27's ~40 MB), trained as the `cpu` preset trains them, exported in float16, HydraFusion's
# deep and attention gates trained on the export (gate split, as the study), measured on the test
# split, packed with its manifest.
#
#   scripts/make_reference_model.sh DATA WORK [OUT]
#
# DATA: the `cpu` study's dataset (`hydrabench study cpu --out X --until generate`, then
# X/stages/generate-*/data); WORK: a scratch directory (resumable: rerun after an interruption);
# OUT: the model directory (default models/cpu-ref). About 40 min on 2 AVX512-BF16 EPYC cores.
set -euo pipefail
DATA=${1:?usage: $0 DATA WORK [OUT]}
WORK=${2:?usage: $0 DATA WORK [OUT]}
OUT=${3:-models/cpu-ref}
H=${HYDRABENCH:-hydrabench}
TRAIN=(train "$DATA" --out "$WORK/paper" --branches radar,camera_right,lidar,radar_lidar --epochs 9 --batch-size 4
       --lr 0.02 --warmup-steps 60 --clip-grad 10 --eval-frames 40 --gate-holdout 0.3 --amp auto --model width=0.5)
$H "${TRAIN[@]}"
[ -f "$WORK/half/checkpoint.pt" ] || $H model export "$WORK/paper" --out "$WORK/half" --name cpu-ref
for g in deep attention; do
  $H train-gate "$WORK/half" "$DATA" --gate "$g" --val-fraction 0.5
done
$H evaluate "$WORK/half" "$DATA" --branches all --fusion soft-nms --bootstrap 500 --json > "$WORK/measured.json"
$H model export "$WORK/half" --out "$OUT" --name cpu-ref --measured "$WORK/measured.json"
