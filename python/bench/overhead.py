"""Overhead of the Python binding per call, on a 256x256 render (hard method, per-vertex
colours, float32: the fused forward of `render_vertex_colors`), against the same library
call timed inside Rust (`_time_render`: inputs already tensors, output kept in Rust), the two
alternating call by call.

    python python/bench/overhead.py [--repeats N] [--rounds R] [--method M] [--subdiv S]

Build the extension in release (`pip install ./python`, or `maturin develop --release`) for
numbers comparable with `tapestry bench`.
"""

import argparse
import time

import numpy as np

import tapestry


def icosphere(subdiv):
    t = (1 + 5 ** 0.5) / 2
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
         [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    v = [list(np.array(p) / np.linalg.norm(p)) for p in v]
    for _ in range(subdiv):
        cache, nf = {}, []

        def mid(a, b):
            k = (min(a, b), max(a, b))
            if k not in cache:
                p = (np.array(v[a]) + np.array(v[b])) / 2
                v.append(list(p / np.linalg.norm(p)))
                cache[k] = len(v) - 1
            return cache[k]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        f = nf
    return np.array(v), np.array(f, dtype=np.int64)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--method", default="hard")
    ap.add_argument("--subdiv", type=int, default=4)
    a = ap.parse_args()
    pos, faces = icosphere(a.subdiv)
    cam = tapestry.perspective_look_at([0, 0, 3], [0, 0, 0], [0, 1, 0], 45.0, 1.0, 0.1, 100.0)
    clip = (np.hstack([pos, np.ones((len(pos), 1))]) @ cam.T).astype(np.float32)
    colors = np.abs(pos).astype(np.float32)
    settings = dict(width=256, height=256, method=a.method)
    for _ in range(10):  # warm-up
        tapestry.render(clip, faces, colors, **settings)
    # Each call timed alone, the two sides alternating call by call, so that both see the same
    # load. The overhead is the median of the paired differences (a call from Python minus the
    # Rust call just before it); the per-side minimum and median are printed beside it.
    rust, py = [], []
    for _ in range(a.rounds * a.repeats):
        rust += tapestry._tapestry._time_render(clip, faces, colors, dict(settings), 1)
        t0 = time.perf_counter()
        tapestry.render(clip, faces, colors, **settings)
        py.append(time.perf_counter() - t0)
    rust, py = np.array(rust), np.array(py)
    print(f"256x256 {a.method}, {len(faces)} faces, float32, {len(py)} calls per side, "
          "alternating")
    for label, r, p in (("min", rust.min(), py.min()),
                        ("median", np.median(rust), np.median(py))):
        print(f"{label:6}: rust library {r * 1e3:.3f} ms, python binding {p * 1e3:.3f} ms")
    d, r = np.median(py - rust), np.median(rust)
    print(f"overhead (median of paired differences): {d * 1e6:.1f} us = {100 * d / r:.2f} % "
          "of the median Rust call")


if __name__ == "__main__":
    main()
