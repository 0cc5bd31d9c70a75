#!/usr/bin/env bash
# Regenerates models/data/ict (and the test fixture) from ICT-FaceKit (MIT licence).
#
#   scripts/convert_ict.sh ICT_REPO
#
# ICT_REPO: a clone of https://github.com/ICT-VGL/ICT-FaceKit (a work tree or a bare git
# directory). The pinned commit's FaceXModel/ is exported to a temporary folder, its files'
# SHA-256 are written to models/data/ict/SOURCES.sha256, and the converter
# (models/examples/convert_ict.rs) writes the model folder and
# models/tests/data/ict_fixture.json. The output is deterministic.
set -euo pipefail
COMMIT=da5f95a607f5e6b37755b38d3385d7f2853732e5
repo=${1:?usage: scripts/convert_ict.sh ICT_REPO}
root=$(cd "$(dirname "$0")/.." && pwd)
if [[ -d "$repo/.git" ]]; then git_dir="$repo/.git"; else git_dir="$repo"; fi
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
git --git-dir="$git_dir" archive "$COMMIT" FaceXModel LICENSE | tar -x -C "$tmp"
out="$root/models/data/ict"
mkdir -p "$out"
(cd "$tmp" && echo "# ICT-FaceKit commit $COMMIT" && sha256sum LICENSE FaceXModel/*.obj FaceXModel/vertex_indices.json) >"$out/SOURCES.sha256"
cp "$tmp/LICENSE" "$out/LICENSE"
cargo run -p tapestry-models --example convert_ict -- "$tmp" "$out" \
  "$root/models/tests/data/ict_fixture.json"
