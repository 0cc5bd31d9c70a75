"""Tapestry: differentiable rendering on the CPU, from Python.

Scenes (the command line's numbers, bit for bit):

- ``render_scene(path, dtype="float64")``: the RGBA image ``[H, W, 4]`` of
  ``tapestry render SCENE --npy``;
- ``grad_scene(path, target, wrt="positions")``: ``(loss, grad)`` of ``tapestry grad``.

The functional API: each op a forward function and a vector-Jacobian product
``*_vjp(..., grad_out, needs=None)`` returning the gradients of ``sum(out * grad_out)``
with respect to the op's differentiable inputs (``None`` where ``needs`` says False):
``render`` (every raster method with its settings), ``rasterize`` / ``interpolate`` /
``blend`` (the hard fragment pipeline), ``texture``, ``shade_sh``, ``shade_phong``.
``tapestry.torch`` wraps them as ``torch.autograd.Function`` (imported only with torch).

Arrays: float inputs are numpy ``float32`` or ``float64`` arrays (every float input of one
call has the same dtype; other dtypes raise ``TypeError``), of any strides; each is copied
once into Rust (the tape owns its values, so it cannot borrow numpy's memory: a memcpy for
C-contiguous arrays, an element walk otherwise). Outputs have the inputs' dtype and are
numpy arrays that own the Rust buffer (no copy). The GIL is released while Rust works. Library errors raise ``TapestryError`` (a
``ValueError``) with the command line's one-line message; shape errors raise ``ValueError``.

Also ``fit_face`` (``tapestry fit-face`` in memory) and ``gradcheck`` / ``gradcheck_scene``
(``tapestry gradcheck``).
"""

import json as _json

from . import _tapestry
from ._tapestry import (  # noqa: F401  (re-exports)
    Fragments,
    TapestryError,
    __version__,
    blend,
    blend_vjp,
    grad_scene,
    interpolate,
    interpolate_vjp,
    perspective_look_at,
    render_scene,
    shade_phong,
    shade_phong_vjp,
    shade_sh,
    shade_sh_vjp,
    texture,
    texture_vjp,
)

#: The raster methods of ``render`` (the library's registry, in its order).
METHODS = _tapestry.METHODS


def _settings(width, height, method, settings):
    d = dict(settings)
    d.update(width=int(width), height=int(height), method=method)
    return d


def render(clip, faces, colors, *, width, height, method="hard", **settings):
    """Image ``[H, W, C + 1]`` of per-vertex ``colors`` ``[V, C]`` over ``faces`` ``[F, 3]``
    from clip positions ``clip`` ``[V, 4]`` with ``method`` (one of ``METHODS``) and its
    settings: ``background`` (C values, default zeros), ``faces_per_pixel``,
    ``cull_backfaces``, ``perspective_correct``, ``sigma``, ``gamma``, ``eps``,
    ``threshold``, ``delta``, ``overdraw_px``, ``near``, ``far`` (defaults: the ops' own,
    docs/CONVENTIONS.md). The last channel is the coverage (or soft alpha)."""
    return _tapestry.render(clip, faces, colors, _settings(width, height, method, settings))


def render_vjp(clip, faces, colors, grad_out, *, width, height, method="hard", needs=None,
               **settings):
    """``(grad_clip, grad_colors)`` of ``sum(render(...) * grad_out)``."""
    return tuple(_tapestry.render_vjp(clip, faces, colors, grad_out,
                                      _settings(width, height, method, settings), needs))


def rasterize(clip, faces, *, width, height, faces_per_pixel=1, cull_backfaces=False,
              perspective_correct=True):
    """Hard rasterization of ``clip`` ``[V, 4]``: a ``Fragments`` object (``offsets``,
    ``face``, ``bary`` ``[N, 3]``, ``depth``, ``view_depth``)."""
    return _tapestry.rasterize(clip, faces, dict(
        width=int(width), height=int(height), faces_per_pixel=faces_per_pixel,
        cull_backfaces=cull_backfaces, perspective_correct=perspective_correct))


def rasterize_vjp(clip, faces, grad_bary, grad_depth, grad_view_depth, *, width, height,
                  faces_per_pixel=1, cull_backfaces=False, perspective_correct=True):
    """``grad_clip`` of ``<bary, grad_bary> + <depth, grad_depth> + <view_depth,
    grad_view_depth>`` (interior gradients: each fragment keeps its face)."""
    return _tapestry.rasterize_vjp(clip, faces, dict(
        width=int(width), height=int(height), faces_per_pixel=faces_per_pixel,
        cull_backfaces=cull_backfaces, perspective_correct=perspective_correct),
        grad_bary, grad_depth, grad_view_depth)


def fit_face(image=None, landmarks=None, *, iters=200, method="hard", size=256, seed=0,
             model=None, face=0):
    """Fits the morphable face model (``tapestry fit-face``, nothing written): to ``image``
    (``[H, W, C]`` float64 in [0, 1], C of 1 to 4) with ``landmarks`` (``[N, 2]`` pixels,
    or detected when None), or to a synthetic target (seed ``seed``) when ``image`` is None.
    ``model``: ``"ict"`` (None: the ICT-FaceKit model), ``"mediapipe"`` (small, fast) or a
    model folder.

    Returns a dict: ``params`` (params.json as a dict), ``report`` (report.json),
    ``vertices`` ``[V, 3]`` (model space, mm), ``faces`` ``[F, 3]``, ``albedo`` ``[V, 3]``,
    ``image`` (the fit's render ``[H, W, 4]``)."""
    p, r, v, f, a, img = _tapestry._fit_face(image, landmarks, iters, method, size, seed,
                                             None if model is None else str(model), face)
    return dict(params=_json.loads(p), report=_json.loads(r), vertices=v, faces=f, albedo=a,
                image=img)


def gradcheck(op=None):
    """Runs the registered gradient checks (``tapestry gradcheck [--op OP] --json``):
    ``(records, passed)``, one dict per case."""
    recs, passed = _tapestry._gradcheck(op)
    return _json.loads(recs), passed


def gradcheck_scene(path, wrt, *, target=None, method=None, samples=8, vertices=48):
    """The scene check of ``tapestry gradcheck SCENE --wrt INPUT --json``:
    ``(report, passed)``."""
    rep, passed = _tapestry._gradcheck_scene(str(path), wrt,
                                             None if target is None else str(target),
                                             method, samples, vertices)
    return _json.loads(rep), passed
