"""Fits a sphere's centre and radius to a silhouette with PyTorch: Tapestry's render as a
torch.autograd.Function (tapestry.torch), loss.backward() and torch.optim.Adam.

    python fit_sphere_torch.py
"""

import torch

import tapestry.torch as tt
from sphere import CAMERA, FACES, SETTINGS, UNIT, target_silhouette


def fit(iters=60, lr=0.05):
    target = torch.from_numpy(target_silhouette())
    camera = torch.from_numpy(CAMERA)
    unit = torch.from_numpy(UNIT)
    colors = torch.ones_like(unit)
    centre = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    radius = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([centre, radius], lr=lr)
    losses = []
    for _ in range(iters):
        opt.zero_grad()
        pos = centre + radius * unit
        clip = torch.cat([pos, torch.ones(len(pos), 1, dtype=pos.dtype)], dim=1) @ camera.T
        img = tt.render(clip, FACES, colors, **SETTINGS)
        loss = ((img[..., 3] - target) ** 2).sum()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return torch.cat([centre.detach(), radius.detach()[None]]).numpy(), losses


if __name__ == "__main__":
    params, losses = fit()
    print(f"loss {losses[0]:.2f} -> {losses[-1]:.4f}")
    print("centre", params[:3].round(3), "radius", params[3].round(3),
          "(target: centre [0.35, -0.2, 0], radius 0.8)")
