"""Fits a sphere's centre and radius to a silhouette with numpy only: Tapestry's render and
its vector-Jacobian product, the chain rule through the camera by hand, and Adam.

    python fit_sphere_numpy.py
"""

import numpy as np

import tapestry
from sphere import CAMERA, FACES, SETTINGS, UNIT, clip_of, target_silhouette


def fit(iters=60, lr=0.05):
    target = target_silhouette()
    params = np.array([0.0, 0.0, 0.0, 0.5])  # centre x, y, z and radius
    m = np.zeros(4)
    v = np.zeros(4)
    colors = np.ones_like(UNIT)
    losses = []
    for t in range(1, iters + 1):
        pos = params[:3] + params[3] * UNIT
        clip = clip_of(pos)
        img = tapestry.render(clip, FACES, colors, **SETTINGS)
        diff = img[..., 3] - target
        losses.append(float(np.sum(diff ** 2)))
        grad_img = np.zeros_like(img)
        grad_img[..., 3] = 2 * diff
        grad_clip, _ = tapestry.render_vjp(clip, FACES, colors, grad_img, needs=[True, False],
                                           **SETTINGS)
        grad_pos = (grad_clip @ CAMERA)[:, :3]  # clip = [p, 1] @ CAMERA.T
        g = np.append(grad_pos.sum(axis=0), np.sum(grad_pos * UNIT))
        m = 0.9 * m + 0.1 * g
        v = 0.999 * v + 0.001 * g ** 2
        params -= lr * (m / (1 - 0.9 ** t)) / (np.sqrt(v / (1 - 0.999 ** t)) + 1e-8)
    return params, losses


if __name__ == "__main__":
    params, losses = fit()
    print(f"loss {losses[0]:.2f} -> {losses[-1]:.4f}")
    print("centre", np.round(params[:3], 3), "radius", round(params[3], 3),
          "(target: centre [0.35, -0.2, 0], radius 0.8)")
