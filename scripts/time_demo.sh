#!/usr/bin/env bash
# Time `make demo` from an empty demo folder (the .venv already built) and record it:
#   scripts/time_demo.sh [OUT.json]     (default: results/demo_time_<date>.json)
# The README's "make demo takes ..." sentence quotes the newest such file (tests/study/test_readme.py).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-results/demo_time_$(date -u +%F).json}
dir=$(mktemp -d /tmp/hydrabench-demo-XXXXXX)
trap 'rm -rf "$dir" "$dir.log"' EXIT
make venv >/dev/null
load=$(cut -d' ' -f1-3 /proc/loadavg)
start=$(date +%s.%N)
make demo DEMO="$dir" >"$dir.log" 2>&1 || { tail -20 "$dir.log" >&2; exit 1; }
end=$(date +%s.%N)
cpu=$(lscpu | sed -n 's/^Model name: *//p' | head -1)
# "AMD EPYC" names two kinds here (with AVX512-BF16, or AVX2 only): the flags tell them apart
flags=$(grep -m1 '^flags' /proc/cpuinfo | tr ' ' '\n' | grep -E '^(avx2|avx512f|avx512_bf16|amx_bf16)$' | paste -sd, -)
.venv/bin/python - "$out" "$start" "$end" "$cpu" "$load" "$(nproc)" "$flags" <<'PY'
import json, sys, datetime
out, start, end, cpu, load, cores, flags = sys.argv[1:]
json.dump({"command": "make demo", "seconds": round(float(end) - float(start), 1), "cpu": cpu, "cpu_flags": flags,
           "cores": int(cores), "load_average_before": load,
           "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")},
          open(out, "w"), indent=1)
print(open(out).read())
PY
