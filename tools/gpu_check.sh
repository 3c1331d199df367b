#!/usr/bin/env bash
# The GPU check: on one GPU, in at most 8 minutes, the numbers the paper's cost tables need
# (tabx_bench/gpu.py, `tabx bench gpu`):
#   - simulator env steps/s at 3v3 and 10v10 (16,384 and 65,536 envs);
#   - MAPPO and IPPO env steps/s at 128 envs x 512 steps (crossfire, medium heuristic);
#   - the paper's UED trial (Robust PLR, zone, 2F1M2Avs2S1K_2L2B2S, 128 envs x 512 steps) run
#     end to end by `tabx train` for 16 steps, then 2 and 4 such trials at once on the GPU
#     (as a sweep's trials with fractional `gpus`), with the minutes projected per 5e7 env
#     steps beside the paper's 18-47 min per UED trial.
# Writes OUT/gpu_check.json, OUT/summary.txt (printed at the end), OUT/ued-*.log and
# OUT/nvidia-smi.txt; a part cut short keeps what the parts before it wrote.
# Usage: tools/gpu_check.sh [OUT [tabx bench gpu options...]]     (OUT default: $OUT, else
#        ./gpu_check); e.g. tools/gpu_check.sh out --concurrency 1,2 --ued-updates 8
set -euo pipefail
out="${1:-${OUT:-gpu_check}}"
shift || true
root="$(cd "$(dirname "$0")/.." && pwd)"
mkdir -p "$out"
out="$(cd "$out" && pwd)"
(nvidia-smi || echo "no nvidia-smi") > "$out/nvidia-smi.txt" 2>&1
# A fresh compilation cache: the first trial compiles cold, the trials after it load.
cache="$(mktemp -d -t tabx-gpu-check-cache-XXXXXX)"
trap 'rm -rf "$cache"' EXIT
export TABX_COMPILE_CACHE_DIR="$cache"
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
cd "$root"
timeout --signal=INT 480 "${PYTHON:-python3}" -m tabx_ued bench gpu --out "$out" "$@"
