"""Bad inputs raise ValueError/TypeError with clear messages; strided inputs work."""

import numpy as np
import pytest

import tapestry
from conftest import PEERS
from test_ops import H, W, mesh


def test_wrong_shapes_raise_value_error():
    clip, faces, colors = mesh()
    with pytest.raises(ValueError, match=r"clip: shape \[7, 3\], expected \[V, 4\]"):
        tapestry.render(clip[:, :3], faces, colors, width=W, height=H)
    with pytest.raises(ValueError, match=r"colors: shape \[6, 3\]"):
        tapestry.render(clip, faces, colors[:6], width=W, height=H)
    with pytest.raises(ValueError, match=r"faces: shape \[3, 2\], expected \[F, 3\]"):
        tapestry.render(clip, faces[:, :2], colors, width=W, height=H)
    with pytest.raises(ValueError, match="grad_out"):
        tapestry.render_vjp(clip, faces, colors, np.zeros((2, 2, 4)), width=W, height=H)
    with pytest.raises(ValueError, match=r"coeffs: shape \[8, 3\], expected \[9, 3\]"):
        tapestry.shade_sh(np.ones((2, 3)), np.ones((2, 3)), np.ones((8, 3)))


def test_wrong_dtypes_raise_type_error():
    clip, faces, colors = mesh()
    with pytest.raises(TypeError, match="clip: dtype int64, expected float32 or float64"):
        tapestry.render(clip.astype(np.int64), faces, colors, width=W, height=H)
    with pytest.raises(TypeError, match="colors: dtype float32, expected float64"):
        tapestry.render(clip, faces, colors.astype(np.float32), width=W, height=H)
    with pytest.raises(TypeError, match="faces: dtype float64, expected an integer dtype"):
        tapestry.render(clip, faces.astype(np.float64), colors, width=W, height=H)
    with pytest.raises(TypeError, match="clip: expected a numpy array, got list"):
        tapestry.render(clip.tolist(), faces, colors, width=W, height=H)
    fr = tapestry.rasterize(clip, faces, width=W, height=H)
    with pytest.raises(TypeError, match="float64 fragments with float32 arrays"):
        tapestry.interpolate(colors.astype(np.float32), fr)


def test_nan_and_bad_values_raise_value_error():
    clip, faces, colors = mesh()
    bad = clip.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"clip\[2, 1\] = NaN is not finite"):
        tapestry.render(bad, faces, colors, width=W, height=H)
    bad = colors.copy()
    bad[0, 0] = np.inf
    with pytest.raises(tapestry.TapestryError, match=r"colors\[0, 0\] = inf is not finite"):
        tapestry.render(clip, faces, bad, width=W, height=H, method="softras")
    with pytest.raises(ValueError, match="normal.* = NaN is not finite"):
        tapestry.shade_sh(np.full((2, 3), np.nan), np.ones((2, 3)), np.ones((9, 3)))
    with pytest.raises(ValueError, match=r"faces\[0, 1\] = -1"):
        tapestry.render(clip, np.array([[0, -1, 2]]), colors, width=W, height=H)
    with pytest.raises(ValueError, match="method 'nope': expected one of hard"):
        tapestry.render(clip, faces, colors, width=W, height=H, method="nope")
    with pytest.raises(ValueError, match="unknown 'sigmaa'"):
        tapestry.render(clip, faces, colors, width=W, height=H, sigmaa=1.0)
    with pytest.raises(ValueError, match="99"):
        tapestry.render(clip, np.array([[0, 1, 99]]), colors, width=W, height=H)
    g = np.zeros((H, W, 4))
    g[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"grad_out\[1, 2, 0\] = NaN is not finite"):
        tapestry.render_vjp(clip, faces, colors, g, width=W, height=H)


def test_library_errors_keep_the_cli_message(tmp_path):
    scene = PEERS / "scenes" / "ico5k_hard.json"
    with pytest.raises(tapestry.TapestryError, match=r"target array: shape \[3, 3, 3\] does "
                       r"not match the scene's image \[128, 128, 3 or 4\]"):
        tapestry.grad_scene(scene, np.zeros((3, 3, 3)))
    with pytest.raises(tapestry.TapestryError, match="--wrt texture: the scene .* has no texture"):
        tapestry.grad_scene(scene, np.zeros((128, 128, 4)), wrt="texture")
    with pytest.raises(ValueError, match="wrt 'normals': expected one of positions"):
        tapestry.grad_scene(scene, np.zeros((128, 128, 4)), wrt="normals")
    with pytest.raises(ValueError, match="nothere.json"):
        tapestry.render_scene(tmp_path / "nothere.json")
    with pytest.raises(ValueError, match="dtype 'float16'"):
        tapestry.render_scene(scene, dtype="float16")


def test_non_contiguous_inputs():
    clip, faces, colors = mesh()
    want = tapestry.render(clip, faces, colors, width=W, height=H, method="softras")
    # Fortran order, a strided slice, reversed rows: the same values in other layouts.
    clip_f = np.asfortranarray(clip)
    wide = np.zeros((7, 8))
    wide[:, ::2] = clip
    clip_s = wide[:, ::2]
    assert not clip_s.flags.c_contiguous
    col_r = colors[::-1].copy()[::-1]
    assert col_r.strides[0] < 0
    faces_t = np.ascontiguousarray(faces.T).T
    assert not faces_t.flags.c_contiguous
    for c, f, col in [(clip_f, faces, colors), (clip_s, faces, colors),
                      (clip, faces_t, col_r), (clip_s, faces_t, col_r)]:
        got = tapestry.render(c, f, col, width=W, height=H, method="softras")
        assert np.array_equal(got, want)
    g = np.ones_like(want)[:, ::-1]
    a = tapestry.render_vjp(clip_s, faces_t, col_r, g, width=W, height=H, method="softras")
    b = tapestry.render_vjp(clip, faces, colors, np.ascontiguousarray(g), width=W, height=H,
                            method="softras")
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    # Broadcast (zero-stride) input.
    n = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (4, 3))
    out = tapestry.shade_sh(n, np.ones((4, 3)), np.ones((9, 3)))
    assert out.shape == (4, 3) and np.all(out == out[0])


def test_contiguous_inputs_are_read_in_place_and_others_copied_once():
    from tapestry import _tapestry
    clip, faces, colors = mesh()
    assert _tapestry._reads_in_place(clip)
    assert _tapestry._reads_in_place(clip.astype(np.float32))
    assert _tapestry._reads_in_place(np.zeros((2, 3, 4)))
    assert not _tapestry._reads_in_place(np.asfortranarray(clip))
    assert not _tapestry._reads_in_place(clip[::2])
    assert not _tapestry._reads_in_place(np.broadcast_to(np.ones(3), (4, 3)))
    # Misaligned memory (a float64 view at a 4-byte offset) is copied, not read in place.
    raw = np.zeros(clip.size * 8 + 4, np.uint8)[4:].view(np.float64).reshape(clip.shape)
    raw[...] = clip
    assert not raw.flags.aligned and not _tapestry._reads_in_place(raw)
    got = tapestry.render(raw, faces, colors, width=W, height=H)
    assert np.array_equal(got, tapestry.render(clip, faces, colors, width=W, height=H))
    # A borrowed input is not written to, and stays usable after the call.
    before = clip.copy()
    tapestry.render_vjp(clip, faces, colors, np.ones((H, W, 4)), width=W, height=H)
    assert np.array_equal(clip, before)


def test_outputs_are_writable_numpy_arrays():
    clip, faces, colors = mesh()
    img = tapestry.render(clip, faces, colors, width=W, height=H)
    assert isinstance(img, np.ndarray) and img.flags.writeable
    img[0, 0, 0] = 5.0


def test_faces_of_every_integer_dtype_render_the_same():
    # int64, int32 and uint32 (C-contiguous) are read in place; the others through numpy's cast.
    clip, faces, colors = mesh()
    want = tapestry.render(clip, faces, colors, width=W, height=H)
    for dt in (np.int64, np.int32, np.uint32, np.uint64, np.int16, np.uint8):
        got = tapestry.render(clip, faces.astype(dt), colors, width=W, height=H)
        assert np.array_equal(got, want), dt
    with pytest.raises(ValueError, match=r"faces\[1, 2\] = -3"):
        bad = faces.astype(np.int32)
        bad[1, 2] = -3
        tapestry.render(clip, bad, colors, width=W, height=H)
    with pytest.raises(ValueError, match=r"faces\[0, 0\] = 4294967296"):
        bad = faces.astype(np.int64)
        bad[0, 0] = 2 ** 32
        tapestry.render(clip, bad, colors, width=W, height=H)
