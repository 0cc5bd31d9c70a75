#!/usr/bin/env bash
# The `raytrace` method side by side with Mitsuba 3 (LLVM, direct_projective) in one run: the
# peers' ico5k sphere and Tapestry's shadow scenes (a ground plane and a quad occluder in one
# mesh, directional or area light) at 256 x 256, 4 spp, 2 threads: speed, image agreement and
# gradient error against one finite-difference reference (scripts/compare_raytrace_mitsuba.py
# says how the conventions are matched and what is timed).
#
#   PEERS_VENV=/path/to/.venv-peers scripts/bench-raytrace-peers.sh [PEERS_DIR] [extra args]
#
# Extra arguments go to compare_raytrace_mitsuba.py (--scenes, --seeds, --ref-spp, --reps,
# --area-edge-samples, --guiding, --mitsuba-reference). Tapestry's binary: $TAPESTRY (default:
# a release build). Dr.Jit needs LLVM >= 17: DRJIT_LIBLLVM_PATH (default: Debian's libllvm19,
# `apt-get install libllvm19`; libLLVM-15 aborts with "Cannot select ... fmaximum").
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
PEERS=${1:-$ROOT/../shared/peers}
shift || true
VENV=${PEERS_VENV:-$ROOT/../.venv-peers}
OUT=${OUT:-${CARGO_TARGET_DIR:-$ROOT/target}/bench-raytrace}
mkdir -p "$OUT"
if [ -z "${TAPESTRY:-}" ]; then
  (cd "$ROOT" && cargo build --release --bin tapestry)
  TAPESTRY=${CARGO_TARGET_DIR:-$ROOT/target}/release/tapestry
fi
export DRJIT_LIBLLVM_PATH=${DRJIT_LIBLLVM_PATH:-/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1}
"$VENV/bin/python" "$ROOT/scripts/compare_raytrace_mitsuba.py" --tapestry "$TAPESTRY" \
  --peers "$PEERS" --out "$OUT" --threads 2 --spp 4 "$@"
