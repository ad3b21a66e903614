#!/usr/bin/env bash
# The device check: train, evaluate and render deliffas on one device and print its numbers
# (docs/performance.md, "GPU"). Runs from a checkout on a bare GPU box: Python 3.12 with torch (CUDA), numpy,
# scipy, h5py, safetensors, opencv-python-headless, matplotlib and tqdm; no open3d, pymeshlab, xatlas, pycolmap,
# trimesh, viser or av. Nothing is installed or downloaded.
#
#   scripts/device_check.sh --prepare [DATA]          # once, on a full install: the small capture (a few MiB)
#   scripts/device_check.sh [--data DATA] [--device cuda|cuda:N|cpu] [--quick] [--json OUT]
#
# DATA (default device_check_data, next to this script's repository) holds shards/ and vendor/ (jaxtyping and
# wadler_lindig, pure Python, put on PYTHONPATH when the box lacks them); carry it with the checkout.
# Exit status: 0 passed, 1 a device-vs-CPU agreement below 50 dB, 2 a usage or set-up error.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
py="${PYTHON:-python3}"
data="$root/device_check_data"
args=()
prepare=0
while [ $# -gt 0 ]; do
  case "$1" in
    --prepare) prepare=1; if [ $# -gt 1 ] && [ "${2#-}" = "$2" ]; then data="$2"; shift; fi ;;
    --data) data="$2"; shift ;;
    *) args+=("$1") ;;
  esac
  shift
done
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
if [ "$prepare" = 1 ]; then
  exec "$py" -m benchmarks.device_check --prepare "$data"
fi
if ! "$py" -c "import jaxtyping" 2>/dev/null; then
  if [ -d "$data/vendor/jaxtyping" ]; then
    export PYTHONPATH="$PYTHONPATH:$data/vendor"
  else
    echo "device_check.sh: jaxtyping is missing and $data/vendor has no copy; run scripts/device_check.sh --prepare on a full install, or: pip install jaxtyping" >&2
    exit 2
  fi
fi
cd "$root"
"$py" -c "import sys, torch; print(f'[device_check] python {sys.version.split()[0]}, torch {torch.__version__}, cuda {torch.version.cuda}, gpus {torch.cuda.device_count()}')"
exec "$py" -m benchmarks.device_check --data "$data" ${args[@]+"${args[@]}"}
