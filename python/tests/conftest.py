"""Shared fixtures: the repository, the `tapestry` binary of the same build, scenes."""

import os
import shutil
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
PEERS = REPO / "render-ops" / "tests" / "data" / "peers"
DATA = REPO / "render-ops" / "tests" / "data"


def _cli_path():
    env = os.environ.get("TAPESTRY_BIN")
    if env:
        return Path(env)
    for profile in ("debug", "release"):
        p = REPO / "target" / profile / "tapestry"
        if p.is_file():
            return p
    return None


@pytest.fixture(scope="session")
def cli():
    """Runs the `tapestry` binary (TAPESTRY_BIN, else target/debug or target/release: the
    CLI of the same checkout, built by `cargo test`/`cargo build`). A missing binary fails."""
    exe = _cli_path()
    assert exe is not None and exe.is_file(), (
        "the tapestry binary is missing: run `cargo build` first or set TAPESTRY_BIN")

    def run(*args):
        out = subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        return out.stdout

    return run


def write_png(path, rgb):
    """A minimal 8-bit RGB PNG writer (no imaging library needed)."""
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + bytes(row) for row in rgb.astype(np.uint8).reshape(h, w * 3))

    def chunk(tag, data):
        return (struct.pack(">I", len(data)) + tag + data
                + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))
    Path(path).write_bytes(png)


@pytest.fixture(scope="session")
def textured_scene(tmp_path_factory):
    """The two-quad uv scene of render-ops/tests/data, textured (8x8 PNG), lit, hard."""
    d = tmp_path_factory.mktemp("textured")
    shutil.copy(DATA / "two_quads_uv.obj", d / "two_quads_uv.obj")
    rng = np.random.default_rng(3)
    write_png(d / "tex.png", rng.integers(0, 256, size=(8, 8, 3)))
    (d / "scene.json").write_text("""{
  "mesh": "two_quads_uv.obj",
  "texture": "tex.png",
  "camera": {"eye": [1, 0.5, 3], "at": [1, 0.5, 0], "up": [0, 1, 0], "fov_y_deg": 45,
             "near": 0.1, "far": 100},
  "image": {"width": 48, "height": 24, "background": [0.1, 0.2, 0.3]},
  "lights": [{"type": "directional", "direction": [0, 0, -1], "color": [1, 1, 1]},
             {"type": "ambient", "color": [0.2, 0.2, 0.2]}],
  "material": {"shading": "lambert", "kd": [0.8, 0.8, 0.8]},
  "raster": {"method": "hard"}
}""")
    return d / "scene.json"


def reference_scenes():
    return sorted(PEERS.glob("scenes/*.json")) + [DATA / "scene_full.json"]
