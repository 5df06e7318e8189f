#!/usr/bin/env bash
# hydrabench on one NVIDIA GPU (issue 15): generate a small `paper` dataset, train the seven-branch
# `paper` network for a fixed number of steps with bf16 AMP, measure training images/s per branch and
# `bench inference --device cuda` (latency, peak GPU memory, NVML energy), print one JSON summary on
# stdout (progress on stderr). Without a GPU the same steps run on the CPU at a smaller size and the
# summary's "skipped" says what was left out. Aim on one GPU: under 8 minutes.
#   scripts/gpu_check.sh [--work DIR] [--steps N] [--frames-per-context N] [--cpu]
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
py="${PYTHON:-}"
if [ -z "$py" ]; then
  if [ -x "$root/.venv/bin/python" ]; then py="$root/.venv/bin/python"; else py=python3; fi
fi
export PYOPENGL_PLATFORM=egl SDL_VIDEODRIVER=offscreen
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
exec "$py" -m study.commands.gpu_check "$@"
