#!/usr/bin/env bash
# Tape speed side by side with PyTorch eager (CPU), in one run: the 50-op elementwise chain over
# 1e6 f32 and the 3DMM linear model (V = 35,000, K = 199), forward + backward, with 1 and 2
# threads, plus the memory bounds criterion measures beside them (autodiff/benches/tape.rs).
#
#   PEERS_VENV=/path/to/.venv-peers scripts/bench-autodiff-peers.sh [PEERS_DIR]
#
# PEERS_DIR defaults to ../shared/peers (the peer kit; its setup.sh makes the venv).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
PEERS=${1:-$ROOT/../shared/peers}
# Criterion writes its results under cargo's target directory (CARGO_TARGET_DIR when set).
TARGET=${CARGO_TARGET_DIR:-$ROOT/target}
case $TARGET in /*) ;; *) TARGET=$ROOT/$TARGET ;; esac # cargo runs in $ROOT below
OUT=${OUT:-$TARGET/bench-peers}
mkdir -p "$OUT"
export PEER_RESULTS_DIR=$OUT
rm -f "$OUT/autograd_micro.jsonl"
for t in 1 2; do
  "$PEERS/py.sh" bench_autograd_micro.py --threads $t --reps 9 >/dev/null
  (cd "$ROOT" && RAYON_NUM_THREADS=$t cargo bench -p tapestry-autodiff --bench tape -- \
    --warm-up-time 1 --measurement-time 3 >"$OUT/tape-$t.txt" 2>&1)
  rm -rf "$OUT/criterion-$t" && cp -r "$TARGET/criterion" "$OUT/criterion-$t"
done
python3 - "$OUT" <<'PY'
import json, os, sys
out = sys.argv[1]
def med(t, group, fn):
    p = os.path.join(out, f"criterion-{t}", group, fn, "new", "estimates.json")
    try:
        return json.load(open(p))["median"]["point_estimate"] / 1e6
    except OSError:
        return float("nan")
torch = [json.loads(l) for l in open(os.path.join(out, "autograd_micro.jsonl"))]
def peer(name, t, **kw):
    for r in torch:
        if r["peer"] == name and r["threads"] == t and all(r.get(k) == v for k, v in kw.items()):
            return r["fwd_bwd"]["median_ms"]
    return float("nan")
print("| case | threads | PyTorch fwd+bwd ms | Tapestry fwd+bwd ms | speed-up | memory bound ms | Tapestry / bound |")
print("|---|---:|---:|---:|---:|---:|---:|")
for t in (1, 2):
    p = peer("torch_chain50", t)
    m = med(t, "chain50", "forward_backward_1e6_f32")
    b = med(t, "chain50", "copy_bound_116x4MB")
    print(f"| chain50, 1e6 f32 | {t} | {p:.1f} | {m:.1f} | {p/m:.2f}x | {b:.1f} | {m/b:.2f} |")
    f = med(t, "chain50", "fused_forward_backward_1e6_f32")
    print(f"| chain50 fused (Tape::fused) | {t} | {p:.1f} | {f:.1f} | {p/f:.2f}x | - | - |")
for t in (1, 2):
    p = peer("torch_3dmm", t, V=35000, K=199)
    m = med(t, "3dmm", "forward_backward_V35000_K199")
    b = med(t, "3dmm", "read_b_twice_bound")
    print(f"| 3DMM V=35000 K=199 | {t} | {p:.2f} | {m:.2f} | {p/m:.2f}x | {b:.2f} | {m/b:.2f} |")
for t in (1, 2):
    for fn in ("record_backward_10k_ops_0d", "record_backward_10k_ops_1"):
        m = med(t, "scalar_chain", fn)
        print(f"| scalar chain {fn} | {t} | - | {m:.3f} | - | - | {m*1e3/1e4:.3f} us/op |")
PY
