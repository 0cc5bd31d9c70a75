"""A sphere mesh and a camera, shared by the two sphere-fitting examples."""

import numpy as np

import tapestry

SIZE = 64


def uv_sphere(rings=12, segments=16):
    """Unit-sphere vertices [V, 3] and triangles [F, 3] (latitude-longitude grid)."""
    verts = [[0.0, 1.0, 0.0]]
    for i in range(1, rings):
        theta = np.pi * i / rings
        for j in range(segments):
            phi = 2 * np.pi * j / segments
            verts.append([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)])
    verts.append([0.0, -1.0, 0.0])
    faces = []
    ring = lambda i, j: 1 + (i - 1) * segments + j % segments  # noqa: E731
    for j in range(segments):
        faces.append([0, ring(1, j + 1), ring(1, j)])
        faces.append([len(verts) - 1, ring(rings - 1, j), ring(rings - 1, j + 1)])
    for i in range(1, rings - 1):
        for j in range(segments):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            faces += [[a, b, d], [a, d, c]]
    return np.array(verts), np.array(faces, dtype=np.int64)


UNIT, FACES = uv_sphere()
# The camera: 4 units in front of the origin, looking at it.
CAMERA = tapestry.perspective_look_at([0, 0, 4], [0, 0, 0], [0, 1, 0], 40.0, 1.0, 0.1, 100.0)
SETTINGS = dict(width=SIZE, height=SIZE, method="softras", sigma=3e-5, gamma=1e-4)


def clip_of(positions):
    """Clip coordinates [V, 4] of world positions [V, 3]."""
    return np.hstack([positions, np.ones((len(positions), 1))]) @ CAMERA.T


def target_silhouette(center=(0.35, -0.2, 0.0), radius=0.8):
    """The alpha channel [H, W] of the sphere to be found."""
    pos = np.asarray(center) + radius * UNIT
    img = tapestry.render(clip_of(pos), FACES, np.ones_like(UNIT), **SETTINGS)
    return img[..., 3]
