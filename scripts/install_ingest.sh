#!/usr/bin/env bash
# Installs the optional person detector of `deliffas ingest`: the [ingest] extra (MediaPipe's run-time
# dependencies) and MediaPipe 0.10.21 itself without its declared dependencies, which would replace
# opencv-contrib-python-headless by the GUI opencv and pull jax and numpy<2. MediaPipe 0.10.21 has wheels for
# Python 3.9-3.12 only; elsewhere this says so and exits 0 (the ingest tests then skip, naming the reason).
set -euo pipefail
PY="${1:-python3}"
if ! "$PY" -c 'import sys; sys.exit(0 if (3, 9) <= sys.version_info[:2] <= (3, 12) else 1)'; then
  echo "install_ingest: MediaPipe 0.10.21 has no wheel for $("$PY" -V); deliffas ingest is unavailable here" >&2
  exit 0
fi
if "$PY" -c 'import mediapipe, sys; sys.exit(0 if mediapipe.__version__ == "0.10.21" else 1)' 2>/dev/null; then
  exit 0
fi
"$PY" -m pip install --quiet "absl-py>=1.0" "attrs>=19.1" "flatbuffers>=2.0" "protobuf>=4.25.3,<5"
"$PY" -m pip install --quiet --no-deps "mediapipe==0.10.21"
