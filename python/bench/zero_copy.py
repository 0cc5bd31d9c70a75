"""What reading float inputs in place saves: `tapestry.texture` on a large texture, called with
the C-contiguous array (read in place by the tape) and with the same values in a layout that
must be copied (a negative-stride view: one numpy copy into C order), alternating call by call,
beside the time of a plain `numpy` copy of the texture (what each call paid before inputs were
borrowed).

    python python/bench/zero_copy.py [--size 1024] [--uv 4096] [--repeats 50] [--dtype float32]

Build the extension in release (`maturin develop --release`) for meaningful numbers.
"""

import argparse
import time

import numpy as np

import tapestry
from tapestry import _tapestry


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--uv", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--dtype", default="float32")
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    tex = rng.random((a.size, a.size, 3)).astype(a.dtype)
    uv = rng.random((a.uv, 2)).astype(a.dtype)
    # The same texture values behind a negative stride: `flipped[::-1]` is `tex`, but it is not
    # C-contiguous, so the binding copies it once (as it copied every input before).
    flipped = np.ascontiguousarray(tex[::-1])[::-1]
    assert np.array_equal(flipped, tex) and not flipped.flags.c_contiguous
    assert _tapestry._reads_in_place(tex) and not _tapestry._reads_in_place(flipped)
    assert np.array_equal(tapestry.texture(tex, uv), tapestry.texture(flipped, uv))
    t_in, t_copy, t_np = [], [], []
    for _ in range(a.repeats):
        t0 = time.perf_counter()
        tapestry.texture(tex, uv)
        t1 = time.perf_counter()
        tapestry.texture(flipped, uv)
        t2 = time.perf_counter()
        tex.copy()
        t3 = time.perf_counter()
        t_in.append(t1 - t0)
        t_copy.append(t2 - t1)
        t_np.append(t3 - t2)
    ms = lambda v: 1e3 * float(np.median(v))  # noqa: E731
    mb = tex.nbytes / 2 ** 20
    print(f"texture {a.size}x{a.size}x3 {a.dtype} ({mb:.1f} MiB), {a.uv} uv, median of "
          f"{a.repeats} alternating calls:")
    print(f"  read in place:   {ms(t_in):8.3f} ms")
    print(f"  copied once:     {ms(t_copy):8.3f} ms  (difference {ms(t_copy) - ms(t_in):.3f} ms)")
    print(f"  numpy tex.copy(): {ms(t_np):7.3f} ms  (the memcpy each call paid before)")


if __name__ == "__main__":
    main()
