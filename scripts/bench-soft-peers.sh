#!/usr/bin/env bash
# SoftRas speed side by side with the PyTorch CPU SoftRas stand-in of the peer kit, in one run,
# on the same scene (the peers' ico5k sphere and camera at 256 x 256, 2 threads), for sigma in
# {1e-3, 1e-4, 1e-5}; see render-ops/benches/soft.rs.
#
#   PEERS_VENV=/path/to/.venv-peers scripts/bench-soft-peers.sh [PEERS_DIR]
#
# PEERS_DIR defaults to ../shared/peers. The stand-in's 80k-face / 512 x 512 case (about 40 s
# and 10 GB per frame) is left out; set FULL=1 to add ico80k at 256 x 256 for sigma 1e-4.
# OUT (default target/bench-peers) receives the scenes, the stand-in's JSONL and criterion's
# text output; criterion's estimates are read from $CARGO_TARGET_DIR/criterion (default target/).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
PEERS=${1:-$ROOT/../shared/peers}
OUT=${OUT:-$ROOT/target/bench-peers}
mkdir -p "$OUT"
export PEER_SCENE_DIR=${PEER_SCENE_DIR:-$OUT/scenes} PEER_RESULTS_DIR=$OUT
rm -f "$OUT/softras_torch.jsonl"
[ -f "$PEER_SCENE_DIR/ico80k.npz" ] || "$PEERS/py.sh" scene_gen.py >/dev/null
for sigma in 1e-3 1e-4 1e-5; do
  "$PEERS/py.sh" bench_softras_torch.py --threads 2 --mesh ico5k --res 256 --sigma $sigma \
    --rgba --reps 3 --warmup 1 >/dev/null
done
if [ "${FULL:-0}" = 1 ]; then
  "$PEERS/py.sh" bench_softras_torch.py --threads 2 --mesh ico80k --res 256 --sigma 1e-4 \
    --rgba --reps 2 --warmup 1 >/dev/null
fi
FILTER='soft_f32/softras.*/5k_faces/256px'
[ "${FULL:-0}" = 1 ] && FILTER='soft_f32/softras.*/(5k_faces|81k_faces)/256px'
(cd "$ROOT" && cargo bench -p tapestry-render-ops --bench soft -- \
  --warm-up-time 1 --measurement-time 3 "$FILTER" >"$OUT/tapestry-soft.txt")
python3 - "$OUT" "${CARGO_TARGET_DIR:-$ROOT/target}/criterion" <<'PY'
import json, os, sys
out, crit = sys.argv[1], sys.argv[2]
def med(fn, par):
    p = os.path.join(crit, "soft_f32", fn.replace("/", "_"), par.replace("/", "_"), "new", "estimates.json")
    try:
        return json.load(open(p))["median"]["point_estimate"] / 1e6
    except OSError:
        return float("nan")
print("| scene | sigma | PyTorch SoftRas fwd / fwd+bwd (2 thr) | PyTorch peak RSS | Tapestry fwd / fwd+bwd (2 thr) | speed-up fwd+bwd |")
print("|---|---|---|---|---|---|")
for line in open(os.path.join(out, "softras_torch.jsonl")):
    r = json.loads(line)
    k = {"ico5k": "5k", "ico80k": "81k"}[r["mesh"]]
    bid = f"{k}_faces/{r['res']}px/2thr"
    name = f"softras_sigma{r['sigma']:.0e}".replace("e-0", "e-")
    f, b = med(f"{name}/forward", bid), med(f"{name}/forward_backward", bid)
    pf, pb = r["forward"]["median_ms"], r["fwd_bwd"]["median_ms"]
    print(f"| {r['mesh']} {r['res']}x{r['res']} | {r['sigma']:.0e} | {pf:.1f} / {pb:.1f} ms | "
          f"{r['maxrss_mb_in_process']:.0f} MB | {f:.2f} / {b:.2f} ms | {pb / b:.0f}x |")
PY
