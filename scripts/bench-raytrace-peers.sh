#!/usr/bin/env bash
# The `raytrace` method's speed side by side with Mitsuba 3 (LLVM, direct_projective) in one
# run: the peers' ico5k sphere at 256 x 256, 4 spp, 2 threads, and Tapestry's shadow scenes
# (a ground plane and a quad occluder in one OBJ, point or area light).
#
#   PEERS_VENV=/path/to/.venv-peers scripts/bench-raytrace-peers.sh [PEERS_DIR]
#
# Tapestry's figures are whole `tapestry render` / `tapestry grad` processes (OBJ load, render,
# output file), best of 3, with the binary in $TAPESTRY (default: a release build); Mitsuba's
# are bench_mitsuba.py's medians (forward, forward+backward of the projective integrator).
# Not yet matched: the Mitsuba side of the shadow scenes and the gradient cosines against a
# common finite-difference reference (issue 32).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
PEERS=${1:-$ROOT/../shared/peers}
VENV=${PEERS_VENV:-$ROOT/../.venv-peers}
OUT=${OUT:-${CARGO_TARGET_DIR:-$ROOT/target}/bench-raytrace}
mkdir -p "$OUT"
if [ -z "${TAPESTRY:-}" ]; then
  (cd "$ROOT" && cargo build --release --bin tapestry)
  TAPESTRY=${CARGO_TARGET_DIR:-$ROOT/target}/release/tapestry
fi
python3 - "$PEERS/scenes" "$OUT" <<'PY'
import json, sys
scenes, out = sys.argv[1], sys.argv[2]
base = json.load(open(f"{scenes}/ico5k.json"))
for name, mesh in [("ico5k", "ico5k.obj"), ("ico5k_target", "ico5k_target.obj")]:
    s = dict(base, mesh=f"{scenes}/{mesh}",
             image={"width": 256, "height": 256, "background": [0, 0, 0]},
             raster={"method": "raytrace", "spp": 4})
    json.dump(s, open(f"{out}/{name}.json", "w"), indent=1)
obj = ["o plane", *[f"v {x} 0 {z} 0.8 0.8 0.8" for x, z in [(-2, -2), (2, -2), (2, 2), (-2, 2)]],
       "f 1 3 2", "f 1 4 3", "o occluder",
       *[f"v {x} {y} {z} 0.9 0.3 0.2" for x, y, z in
         [(-0.45, 0.8, -0.25), (0.15, 0.8, -0.2), (0.1, 0.8, 0.25), (-0.4, 0.85, 0.25)]],
       "f 5 7 6", "f 5 8 7"]
open(f"{out}/shadow.obj", "w").write("\n".join(obj) + "\n")
lights = {
    "shadow_point": [{"type": "ambient", "color": [0.1] * 3},
                     {"type": "point", "position": [-0.6, 3, 0.2], "color": [1, 1, 1]}],
    "shadow_area": [{"type": "ambient", "color": [0.1] * 3},
                    {"type": "area", "corner": [-0.9, 3, -0.3], "edge_u": [0.6, 0, 0],
                     "edge_v": [0, 0, 0.6], "radiance": [3, 3, 3]}],
}
for name, l in lights.items():
    s = {"mesh": "shadow.obj", "camera": {"eye": [0, 3, 2.5], "at": [0, 0, 0], "fov_y_deg": 45},
         "image": {"width": 256, "height": 256, "background": [0, 0, 0]}, "lights": l,
         "material": {"shading": "lambert"}, "raster": {"method": "raytrace", "spp": 4}}
    json.dump(s, open(f"{out}/{name}.json", "w"), indent=1)
PY
export RAYON_NUM_THREADS=2
best() { # best of 3 wall times of a command, in seconds
  local b=1e9
  for _ in 1 2 3; do
    local t0=$(date +%s.%N); "$@" >/dev/null 2>&1; local t1=$(date +%s.%N)
    b=$(python3 -c "print(round(min($b, $t1 - $t0), 3))")
  done
  echo "$b"
}
"$TAPESTRY" render "$OUT/ico5k_target.json" --out "$OUT/t.png" --npy "$OUT/t.npy" >/dev/null
for sc in ico5k shadow_point shadow_area; do
  f=$(best "$TAPESTRY" render "$OUT/$sc.json" --out "$OUT/$sc.png")
  fb=$(best "$TAPESTRY" grad "$OUT/$sc.json" --target "$OUT/t.npy" --wrt positions --out "$OUT/g.npy")
  echo "tapestry $sc 256x256 spp 4, 2 threads: forward ${f} s, forward+backward ${fb} s"
done
# Needs LLVM >= 17 for Dr.Jit (py.sh: DRJIT_LIBLLVM_PATH).
PEERS_VENV=$VENV "$PEERS/py.sh" bench_mitsuba.py --threads 2 --mesh ico5k --res 256 --spp 4
