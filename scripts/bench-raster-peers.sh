#!/usr/bin/env bash
# Hard-rasterizer speed side by side with DEODR's CPU renderer, in one run, on the same scenes
# (the peers' ico5k / ico80k spheres and camera, see render-ops/benches/raster.rs).
#
#   PEERS_VENV=/path/to/.venv-peers scripts/bench-raster-peers.sh [PEERS_DIR]
#
# PEERS_DIR defaults to ../shared/peers (the peer kit; its setup.sh makes the venv). Prints one
# line per scene: DEODR's median forward / forward+backward (1 thread; its C++ core is
# single-threaded) and Tapestry's criterion medians (full pipeline and bare rasterizer kernel,
# 1 and 2 threads).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
PEERS=${1:-$ROOT/../shared/peers}
OUT=${OUT:-${CARGO_TARGET_DIR:-$ROOT/target}/bench-peers}
mkdir -p "$OUT"
export PEER_SCENE_DIR=${PEER_SCENE_DIR:-$OUT/scenes} PEER_RESULTS_DIR=$OUT
rm -f "$OUT/deodr.jsonl"
[ -f "$PEER_SCENE_DIR/ico80k.npz" ] || "$PEERS/py.sh" scene_gen.py >/dev/null
for mesh in ico5k ico80k; do
  for res in 256 512; do
    "$PEERS/py.sh" bench_deodr.py --threads 1 --mesh $mesh --res $res --reps 9 >/dev/null
  done
done
(cd "$ROOT" && cargo bench -p tapestry-render-ops --bench raster -- \
  --warm-up-time 1 --measurement-time 3 'raster_forward_f32|render_hard_f32|deodr_f32' >"$OUT/tapestry.txt")
python3 - "$OUT" <<'PY'
import json, os, sys
out = sys.argv[1]
crit = os.path.join(out, "..", "criterion")
def med(group, bid):
    # criterion's folders: <group>/[<function>/]<parameter with '/' made '_'>
    fn, _, par = bid.partition("|")
    parts = [group] + ([fn] if par else []) + [(par or fn).replace("/", "_")]
    p = os.path.join(crit, *parts, "new", "estimates.json")
    try:
        return json.load(open(p))["median"]["point_estimate"] / 1e6
    except OSError:
        return float("nan")
print("| scene | DEODR fwd (1 thr) | DEODR fwd+bwd (1 thr) | Tapestry render fwd 1 / 2 thr | Tapestry fwd+bwd 1 / 2 thr | raster kernel (cull) 1 / 2 thr | speed-up fwd, 2 thr |")
print("|---|---|---|---|---|---|---|")
rows = []
for line in open(os.path.join(out, "deodr.jsonl")):
    r = json.loads(line)
    k = {"ico5k": "5k", "ico80k": "81k"}[r["mesh"]]
    res = r["res"]
    bid = f"{k}_faces/{res}px"
    f1, f2 = med("render_hard_f32", f"forward|{bid}/1thr"), med("render_hard_f32", f"forward|{bid}/2thr")
    b1, b2 = med("render_hard_f32", f"forward_backward|{bid}/1thr"), med("render_hard_f32", f"forward_backward|{bid}/2thr")
    k1, k2 = med("raster_forward_f32", f"{bid}/1thr/cull"), med("raster_forward_f32", f"{bid}/2thr/cull")
    d, db = r["forward"]["median_ms"], r["fwd_bwd"]["median_ms"]
    print(f"| {r['mesh']} {res}x{res} | {d:.2f} ms | {db:.2f} ms | {f1:.2f} / {f2:.2f} ms | {b1:.2f} / {b2:.2f} ms | {k1:.2f} / {k2:.2f} ms | {d / f2:.1f}x |")
    rows.append((r, bid, d, db))
print()
print("Tapestry `deodr` (DEODR's settings: culling, screen-space colours, 1 px ramp) against DEODR:")
print()
print("| scene | DEODR fwd / fwd+bwd (1 thr) | deodr fwd 1 / 2 thr | deodr fwd+bwd 1 / 2 thr | speed-up fwd+bwd 1 / 2 thr |")
print("|---|---|---|---|---|")
for r, bid, d, db in rows:
    f1, f2 = med("deodr_f32", f"forward|{bid}/1thr"), med("deodr_f32", f"forward|{bid}/2thr")
    b1, b2 = med("deodr_f32", f"forward_backward|{bid}/1thr"), med("deodr_f32", f"forward_backward|{bid}/2thr")
    print(f"| {r['mesh']} {r['res']}x{r['res']} | {d:.2f} / {db:.2f} ms | {f1:.2f} / {f2:.2f} ms | {b1:.2f} / {b2:.2f} ms | {db / b1:.2f}x / {db / b2:.2f}x |")
PY
