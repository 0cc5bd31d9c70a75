"""PyTorch bridge: ``torch.autograd.Function`` wrappers over Tapestry's forward and
vector-Jacobian functions, for CPU tensors (float32 or float64).

    import tapestry.torch as tt
    image = tt.render(clip, faces, colors, width=64, height=64, method="softras")
    loss = ((image - target) ** 2).sum()
    loss.backward()            # gradients reach clip and colors

Each backward calls the op's ``*_vjp`` with ``needs`` set from ``ctx.needs_input_grad``, so
no gradient is computed for inputs that do not require one. Tensors cross as numpy views
(``Tensor.numpy()``, no copy); results come back with ``torch.from_numpy`` (no copy).
Backward functions are not themselves differentiable (no double backward).
"""

import numpy as _np
import torch as _torch

from . import _tapestry
from . import _settings

__all__ = ["render", "rasterize", "interpolate", "blend", "texture", "shade_sh",
           "shade_phong"]


def _n(t):
    if t.device.type != "cpu":
        raise ValueError(f"tapestry.torch: CPU tensors only, got a tensor on {t.device}")
    return t.detach().numpy()


def _t(a):
    return None if a is None else _torch.from_numpy(_np.asarray(a))


def _function(name, forward, vjp):
    """An autograd Function over ``forward(arrays, extra)`` and
    ``vjp(arrays, grad, extra, needs)`` (``arrays``: the differentiable tensor inputs as numpy
    arrays; ``extra``: the other arguments)."""

    class Op(_torch.autograd.Function):
        @staticmethod
        def forward(ctx, extra, *tensors):
            ctx.save_for_backward(*tensors)
            ctx.extra = extra
            return _t(forward([_n(t) for t in tensors], extra))

        @staticmethod
        @_torch.autograd.function.once_differentiable
        def backward(ctx, grad):
            tensors = ctx.saved_tensors
            needs = list(ctx.needs_input_grad[1:])
            if not any(needs):
                return (None,) * (1 + len(tensors))
            grads = vjp([_n(t) for t in tensors], _n(grad.contiguous()), ctx.extra, needs)
            return (None,) + tuple(_t(g) if n else None for g, n in zip(grads, needs))

    Op.__name__ = Op.__qualname__ = name
    return Op


def _faces(faces):
    if isinstance(faces, _torch.Tensor):
        faces = faces.detach().cpu().numpy()
    return _np.asarray(faces)


_Render = _function(
    "Render",
    lambda a, e: _tapestry.render(a[0], e[0], a[1], e[1]),
    lambda a, g, e, needs: _tapestry.render_vjp(a[0], e[0], a[1], g, e[1], needs),
)


def render(clip, faces, colors, *, width, height, method="hard", **settings):
    """``tapestry.render`` on tensors: differentiable in ``clip`` [V, 4] and ``colors`` [V, C]."""
    return _Render.apply((_faces(faces), _settings(width, height, method, settings)), clip, colors)


class _Rasterize(_torch.autograd.Function):
    @staticmethod
    def forward(ctx, faces, settings, clip):
        frags = _tapestry.rasterize(_n(clip), faces, settings)
        ctx.save_for_backward(clip)
        ctx.extra = (faces, settings)
        # The fragment layout (a non-tensor output) passes through without a gradient.
        return _t(frags.bary), _t(frags.depth), _t(frags.view_depth), frags

    @staticmethod
    @_torch.autograd.function.once_differentiable
    def backward(ctx, gb, gd, gv, _):
        (clip,) = ctx.saved_tensors
        faces, settings = ctx.extra
        g = _tapestry.rasterize_vjp(_n(clip), faces, settings, _n(gb.contiguous()),
                                    _n(gd.contiguous()), _n(gv.contiguous()))
        return None, None, _t(g)


def rasterize(clip, faces, *, width, height, faces_per_pixel=1, cull_backfaces=False,
              perspective_correct=True):
    """Hard rasterization: ``(fragments, bary, depth, view_depth)``; the three tensors are
    differentiable in ``clip`` (interior gradients), ``fragments`` is the fixed layout that
    ``interpolate`` and ``blend`` take."""
    settings = dict(width=int(width), height=int(height), faces_per_pixel=faces_per_pixel,
                    cull_backfaces=cull_backfaces, perspective_correct=perspective_correct)
    bary, depth, view_depth, frags = _Rasterize.apply(_faces(faces), settings, clip)
    return frags, bary, depth, view_depth


_Interpolate = _function(
    "Interpolate",
    lambda a, e: _tapestry.interpolate(a[0], e, a[1]),
    lambda a, g, e, needs: _tapestry.interpolate_vjp(a[0], e, g, a[1], needs),
)


def interpolate(attributes, fragments, bary):
    """Vertex attributes [V, C] at the fragments: [N, C], differentiable in both."""
    return _Interpolate.apply(fragments, attributes, bary)


_Blend = _function(
    "Blend",
    lambda a, e: _tapestry.blend(a[0], e[0], e[1]),
    lambda a, g, e, needs: [_tapestry.blend_vjp(a[0], e[0], g, e[1])],
)


def blend(colors, fragments, background=None):
    """Hard compositing of fragment colours [N, C]: the image [H, W, C + 1]."""
    return _Blend.apply((fragments, None if background is None else list(background)), colors)


_Texture = _function(
    "Texture",
    lambda a, e: _tapestry.texture(a[0], a[1], *e),
    lambda a, g, e, needs: _tapestry.texture_vjp(a[0], a[1], g, *e, needs),
)


def texture(texels, uv, filter="bilinear", wrap="repeat"):
    """Texels [H, W, C] sampled at uv [N, 2]: [N, C], differentiable in both."""
    return _Texture.apply((filter, wrap), texels, uv)


_ShadeSh = _function(
    "ShadeSh",
    lambda a, e: _tapestry.shade_sh(*a),
    lambda a, g, e, needs: _tapestry.shade_sh_vjp(*a, g, needs),
)


def shade_sh(normal, albedo, coeffs):
    """SH lighting [N, 3] of normals [N, 3], albedo [N, 3] or [3], coefficients [9, 3]."""
    return _ShadeSh.apply(None, normal, albedo, coeffs)


_ShadePhong = _function(
    "ShadePhong",
    lambda a, e: _tapestry.shade_phong(*a[:9], e, *a[9:]),
    lambda a, g, e, needs: _tapestry.shade_phong_vjp(*a[:9], g, e, needs, *a[9:]),
)


def shade_phong(position, normal, albedo, eye, ambient, light_dir, light_color, ks, shininess,
                model="lambert", point_position=None, point_color=None):
    """The Lambert / Phong / Blinn-Phong model [N, 3], differentiable in all its inputs
    (``point_position`` and ``point_color`` [P, 3]: point lights, both or neither)."""
    points = tuple(x for x in (point_position, point_color) if x is not None)
    if len(points) == 1:
        raise ValueError("point_position and point_color: give both or neither")
    return _ShadePhong.apply(model, position, normal, albedo, eye, ambient, light_dir,
                             light_color, ks, shininess, *points)
