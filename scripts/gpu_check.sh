#!/usr/bin/env bash
# hydrabench on one NVIDIA GPU (issues 15, 29; docs/gpu.md): generate a small `paper` dataset (or,
# where the renderer cannot start, train on synthetic tensors and say so), time the seven-branch
# network's training steps with bf16 AMP, run `bench inference` on the GPU (latency, peak GPU memory,
# NVML energy), and print one JSON summary on stdout (progress on stderr). Without a GPU the same
# steps run on the CPU at a smaller size and the summary's "skipped" says what was left out.
#   scripts/gpu_check.sh [--work DIR] [--steps N] [--frames-per-context N] [--contexts A,B]
#                        [--device auto|cpu] [--parts generate,train,bench] [--json FILE] [--budget-s 300]
# First every third-party module the check imports is tried (scripts/device_kit.py check); where one
# is missing and the device kit was carried (.whl/), its wheels are installed into a scratch site
# ($KIT_SITE, default /tmp/site; $KIT_WHEELS: another wheel folder) and the modules tried again; what is still missing is named on one
# line (exit 3). Where $OUT is set (the `device` tool's output folder) and
# no --json is given, the summary also goes to $OUT/gpu_check.json, rewritten after every step.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
py="${PYTHON:-}"
if [ -z "$py" ]; then
  if [ -x "$root/.venv/bin/python" ]; then py="$root/.venv/bin/python"; else py=python3; fi
fi
export PYOPENGL_PLATFORM=egl SDL_VIDEODRIVER=offscreen PYTHONUNBUFFERED=1
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
if ! missing=$("$py" "$root/scripts/device_kit.py" check); then
  shopt -s nullglob
  wheels=("${KIT_WHEELS:-$root/.whl}"/*.whl)
  if [ ${#wheels[@]} -eq 0 ]; then
    echo "$missing" >&2
    exit 3
  fi
  site="${KIT_SITE:-/tmp/site}"
  if ! log=$("$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" \
      "${wheels[@]}" 2>&1); then
    echo "gpu_check: the device kit did not install into $site: $(printf '%s\n' "$log" | grep -m1 -i error || printf '%s\n' "$log" | tail -1)" >&2
    exit 3
  fi
  export PYTHONPATH="$root:$site${PYTHONPATH#"$root"}"
  if ! missing=$("$py" "$root/scripts/device_kit.py" check); then
    echo "$missing" >&2
    exit 3
  fi
fi
args=("$@")
if [ -n "${OUT:-}" ] && [[ " $* " != *" --json "* ]]; then
  args+=(--json "$OUT/gpu_check.json")
fi
exec "$py" -m study.commands.gpu_check "${args[@]}"
