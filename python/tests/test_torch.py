"""The PyTorch bridge: torch.autograd.gradcheck through every wrapped op (float64, CPU).
Skipped only when torch is not installed."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
import tapestry.torch as tt  # noqa: E402

from test_ops import H, W, mesh  # noqa: E402


def _t(a):
    return torch.tensor(a, dtype=torch.float64, requires_grad=True)


def test_render_gradcheck_softras():
    clip, faces, colors = mesh()
    kw = dict(width=W, height=H, method="softras", sigma=1e-3, gamma=1e-2)
    assert torch.autograd.gradcheck(
        lambda c, col: tt.render(c, faces, col, **kw), (_t(clip), _t(colors)),
        eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("method", ["hard", "deodr", "dibr"])
def test_render_gradcheck_methods(method):
    clip, faces, colors = mesh(1)
    assert torch.autograd.gradcheck(
        lambda c, col: tt.render(c, faces, col, width=W, height=H, method=method),
        (_t(clip), _t(colors)), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_fragment_pipeline_gradcheck():
    clip, faces, colors = mesh(2)

    def f(c, col):
        fr, bary, _, _ = tt.rasterize(c, faces, width=W, height=H)
        return tt.blend(tt.interpolate(col, fr, bary), fr, [0.1, 0.2, 0.3])

    assert torch.autograd.gradcheck(f, (_t(clip), _t(colors)), eps=1e-6, atol=1e-5,
                                    rtol=1e-4)


def test_shading_and_texture_gradcheck():
    rng = np.random.default_rng(0)
    assert torch.autograd.gradcheck(
        tt.shade_sh, (_t(rng.standard_normal((5, 3))), _t(rng.uniform(size=(5, 3))),
                      _t(rng.standard_normal((9, 3)))))
    assert torch.autograd.gradcheck(
        lambda t, u: tt.texture(t, u), (_t(rng.uniform(size=(4, 5, 3))),
                                        _t(rng.uniform(0.1, 0.9, size=(6, 2)))))
    ins = [rng.standard_normal((4, 3)), rng.standard_normal((4, 3)) + [0, 0, 3],
           rng.uniform(size=(4, 3)), [0.3, 0.2, 5.0], [0.1, 0.2, 0.1],
           [[0.2, -0.1, -1.0]], [[0.9, 0.8, 0.7]], [0.5, 0.4, 0.3], [8.0]]
    assert torch.autograd.gradcheck(
        lambda *a: tt.shade_phong(*a, model="blinn_phong"), tuple(_t(np.array(x)) for x in ins))
    points = [[[1.5, 2.0, 6.0]], [[0.6, 0.7, 0.8]]]
    assert torch.autograd.gradcheck(
        lambda *a: tt.shade_phong(*a[:9], model="phong", point_position=a[9],
                                  point_color=a[10]),
        tuple(_t(np.array(x)) for x in ins + points))


def test_backward_in_a_training_step():
    clip, faces, colors = mesh(3)
    c = torch.tensor(clip, dtype=torch.float32, requires_grad=True)
    col = torch.tensor(colors, dtype=torch.float32, requires_grad=True)
    img = tt.render(c, faces, col, width=W, height=H, method="softras")
    loss = (img ** 2).sum()
    loss.backward()
    assert c.grad.shape == c.shape and col.grad.shape == col.shape
    assert torch.isfinite(c.grad).all() and c.grad.abs().sum() > 0
    # Only what requires a gradient gets one.
    col2 = torch.tensor(colors, dtype=torch.float32, requires_grad=True)
    tt.render(torch.tensor(clip, dtype=torch.float32), faces, col2, width=W, height=H).sum().backward()
    assert col2.grad is not None
