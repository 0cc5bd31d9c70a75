"""The functional ops: each VJP against float64 central differences of its own forward."""

import numpy as np
import pytest

import tapestry

W, H = 16, 12


def mesh(seed=0, dtype=np.float64):
    """Three triangles in clip space (w != 1: perspective), overlapping, inside the image."""
    rng = np.random.default_rng(seed)
    clip = np.array([
        [-0.8, -0.7, 0.1, 1.0], [0.7, -0.6, 0.2, 1.1], [-0.1, 0.8, 0.3, 0.9],
        [-0.5, 0.6, -0.2, 1.2], [0.6, 0.7, 0.0, 1.0], [0.1, -0.8, 0.4, 1.05],
        [0.9, 0.1, 0.5, 1.0],
    ]) + rng.uniform(-0.02, 0.02, size=(7, 4)) * [1, 1, 1, 0]
    faces = np.array([[0, 1, 2], [3, 5, 4], [1, 6, 4]], dtype=np.int64)
    colors = rng.uniform(0.1, 0.9, size=(7, 3))
    return clip.astype(dtype), faces, colors.astype(dtype)


def fd_check(f, vjp, inputs, which, seed=0, eps=1e-6, rtol=1e-6, atol=1e-8, directions=3):
    """<vjp(x, g)[i], d> against (<f(x + eps d), g> - <f(x - eps d), g>) / (2 eps)."""
    rng = np.random.default_rng(seed)
    out = f(*inputs)
    outs = out if isinstance(out, tuple) else (out,)
    gs = tuple(rng.standard_normal(o.shape) for o in outs)
    grads = vjp(*inputs, *gs)
    assert len(grads) == len(inputs)

    def dot(x):
        o = f(*x)
        o = o if isinstance(o, tuple) else (o,)
        return sum(float(np.sum(a * g)) for a, g in zip(o, gs))

    for i in which:
        assert grads[i] is not None and grads[i].shape == inputs[i].shape
        for _ in range(directions):
            d = rng.standard_normal(inputs[i].shape)
            xp = list(inputs)
            xm = list(inputs)
            xp[i] = inputs[i] + eps * d
            xm[i] = inputs[i] - eps * d
            numeric = (dot(xp) - dot(xm)) / (2 * eps)
            analytic = float(np.sum(grads[i] * d))
            assert abs(analytic - numeric) <= atol + rtol * max(abs(numeric), 1.0), (
                i, analytic, numeric)


@pytest.mark.parametrize("method", tapestry.METHODS)
def test_render_vjp_colors(method):
    clip, faces, colors = mesh()
    kw = dict(width=W, height=H, method=method, background=[0.2, 0.3, 0.4])
    fd_check(lambda c, col: tapestry.render(c, faces, col, **kw),
             lambda c, col, g: tapestry.render_vjp(c, faces, col, g, **kw),
             [clip, colors], which=[1])


@pytest.mark.parametrize("method", ["hard", "deodr", "softras", "dibr"])
def test_render_vjp_clip(method):
    clip, faces, colors = mesh(1)
    kw = dict(width=W, height=H, method=method)
    if method == "softras":
        kw.update(sigma=1e-3, gamma=1e-2)
    fd_check(lambda c, col: tapestry.render(c, faces, col, **kw),
             lambda c, col, g: tapestry.render_vjp(c, faces, col, g, **kw),
             [clip, colors], which=[0], rtol=1e-5)


def test_needs_skips_gradients():
    clip, faces, colors = mesh()
    img = tapestry.render(clip, faces, colors, width=W, height=H)
    gc, gcol = tapestry.render_vjp(clip, faces, colors, np.ones_like(img), width=W, height=H,
                                   needs=[False, True])
    assert gc is None and gcol.shape == colors.shape


def test_rasterize_interpolate_blend_chain():
    clip, faces, colors = mesh(2)
    fr = tapestry.rasterize(clip, faces, width=W, height=H)
    assert fr.width == W and fr.height == H and len(fr) > 0
    assert fr.offsets.shape == (W * H + 1,) and fr.offsets[-1] == len(fr)
    col = tapestry.interpolate(colors, fr)
    img = tapestry.blend(col, fr, [0.0, 0.0, 0.0])
    # The chain is the hard render.
    assert np.allclose(img, tapestry.render(clip, faces, colors, width=W, height=H),
                       rtol=0, atol=1e-12)


def test_rasterize_vjp():
    clip, faces, _ = mesh(3)
    kw = dict(width=W, height=H)
    n = len(tapestry.rasterize(clip, faces, **kw))

    def f(c):
        fr = tapestry.rasterize(c, faces, **kw)
        assert len(fr) == n
        return fr.bary, fr.depth, fr.view_depth

    fd_check(f, lambda c, gb, gd, gv: (tapestry.rasterize_vjp(c, faces, gb, gd, gv, **kw),),
             [clip], which=[0], rtol=1e-5)


def test_interpolate_vjp():
    clip, faces, colors = mesh(4)
    fr = tapestry.rasterize(clip, faces, width=W, height=H)
    bary = fr.bary
    fd_check(lambda a, b: tapestry.interpolate(a, fr, b),
             lambda a, b, g: tapestry.interpolate_vjp(a, fr, g, b),
             [colors, bary], which=[0, 1])


def test_blend_vjp():
    clip, faces, colors = mesh(5)
    fr = tapestry.rasterize(clip, faces, width=W, height=H)
    col = tapestry.interpolate(colors, fr)
    fd_check(lambda c: tapestry.blend(c, fr, [0.1, 0.2, 0.3]),
             lambda c, g: (tapestry.blend_vjp(c, fr, g, [0.1, 0.2, 0.3]),),
             [col], which=[0])


@pytest.mark.parametrize("filt", ["nearest", "bilinear"])
@pytest.mark.parametrize("wrap", ["repeat", "clamp", "mirror"])
def test_texture_vjp(filt, wrap):
    rng = np.random.default_rng(6)
    tex = rng.uniform(size=(5, 7, 3))
    uv = rng.uniform(0.05, 0.95, size=(11, 2))
    which = [0] if filt == "nearest" else [0, 1]
    fd_check(lambda t, u: tapestry.texture(t, u, filt, wrap),
             lambda t, u, g: tapestry.texture_vjp(t, u, g, filt, wrap),
             [tex, uv], which=which)


def test_shade_sh_vjp():
    rng = np.random.default_rng(7)
    n = rng.standard_normal((9, 3))
    alb = rng.uniform(size=(9, 3))
    co = rng.standard_normal((9, 3)) * 0.3
    fd_check(tapestry.shade_sh, tapestry.shade_sh_vjp, [n, alb, co], which=[0, 1, 2])


def phong_inputs(seed, n=6):
    """Fragments in front of the eye, two directional and two point lights."""
    rng = np.random.default_rng(seed)
    base = [rng.standard_normal((n, 3)), rng.standard_normal((n, 3)) + [0, 0, 3],
            rng.uniform(size=(n, 3)), np.array([0.3, 0.2, 5.0]), np.array([0.1, 0.2, 0.1]),
            np.array([[0.2, -0.1, -1.0], [-0.3, 0.4, -0.8]]), rng.uniform(size=(2, 3)),
            np.array([0.5, 0.4, 0.3]), np.array([12.0])]
    points = [np.array([[1.5, 2.0, 6.0], [-2.0, 0.5, 4.0]]), rng.uniform(size=(2, 3))]
    return base, points


@pytest.mark.parametrize("model", ["lambert", "phong", "blinn_phong"])
@pytest.mark.parametrize("with_points", [False, True])
def test_shade_phong_vjp(model, with_points):
    base, points = phong_inputs(8)
    ins = base + points if with_points else base
    k = len(ins)

    def f(*a):
        return tapestry.shade_phong(*a[:9], model=model, point_position=a[9] if k > 9 else None,
                                    point_color=a[10] if k > 9 else None)

    def vjp(*a):
        return tapestry.shade_phong_vjp(*a[:9], a[k], model=model,
                                        point_position=a[9] if k > 9 else None,
                                        point_color=a[10] if k > 9 else None)

    fd_check(f, vjp, ins, which=range(k), rtol=1e-5)


def test_shade_phong_point_lights_lambert_reference():
    """Point lights in numpy: albedo * (ambient + sum_l max(0, n . unit(p_l - x)) c_l)
    (render_ops::shade::phong, no distance fall-off), without directional lights."""
    (x, nrm, alb, eye, amb, _, _, ks, sh), (pp, pc) = phong_inputs(9)
    none = np.zeros((0, 3))
    got = tapestry.shade_phong(x, nrm, alb, eye, amb, none, none, ks, sh,
                               point_position=pp, point_color=pc)
    n = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    want = alb * amb
    for p, c in zip(pp, pc):
        to = p - x
        ndl = np.sum(n * to / np.linalg.norm(to, axis=1, keepdims=True), axis=1, keepdims=True)
        want = want + alb * np.maximum(ndl, 0) * c
    assert np.allclose(got, want, rtol=1e-12, atol=1e-12)
    # The float32 path agrees.
    got32 = tapestry.shade_phong(*(np.asarray(a, np.float32) for a in
                                   (x, nrm, alb, eye, amb, none, none, ks, sh)),
                                 point_position=pp.astype(np.float32),
                                 point_color=pc.astype(np.float32))
    assert got32.dtype == np.float32 and np.abs(got32 - want).max() < 1e-5
    with pytest.raises(ValueError, match="point_position and point_color: give both"):
        tapestry.shade_phong(x, nrm, alb, eye, amb, none, none, ks, sh, point_position=pp)
    with pytest.raises(ValueError, match=r"point_color: shape \[1, 3\], expected \[P, 3\]"):
        tapestry.shade_phong(x, nrm, alb, eye, amb, none, none, ks, sh, point_position=pp,
                             point_color=pc[:1])


def test_float32_matches_float64():
    clip, faces, colors = mesh()
    for method in tapestry.METHODS:
        a = tapestry.render(clip, faces, colors, width=W, height=H, method=method)
        b = tapestry.render(clip.astype(np.float32), faces, colors.astype(np.float32),
                            width=W, height=H, method=method)
        assert b.dtype == np.float32
        assert np.abs(a - b).max() < 1e-4, method


def test_perspective_look_at():
    m = tapestry.perspective_look_at([0, 0, 3], [0, 0, 0], [0, 1, 0], 45.0, 1.0, 0.1, 100.0)
    assert m.shape == (4, 4)
    p = m @ np.array([0.0, 0.0, 0.0, 1.0])
    assert abs(p[0]) < 1e-12 and abs(p[1]) < 1e-12 and p[3] > 0
