"""The sphere-fitting examples converge (few iterations, the examples' own code)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))


def test_fit_sphere_numpy():
    import fit_sphere_numpy

    params, losses = fit_sphere_numpy.fit(iters=40)
    assert losses[-1] < 0.2 * losses[0]
    assert np.abs(params[:2] - [0.35, -0.2]).max() < 0.15


def test_fit_sphere_torch():
    pytest.importorskip("torch")
    import fit_sphere_torch

    params, losses = fit_sphere_torch.fit(iters=40)
    assert losses[-1] < 0.2 * losses[0]
    assert np.abs(params[:2] - [0.35, -0.2]).max() < 0.15
