"""fit_face and gradcheck through the bindings."""

import numpy as np
import pytest

import tapestry
from conftest import PEERS


def test_fit_face_synthetic():
    r = tapestry.fit_face(iters=4, size=64, seed=1)
    v, f, a, img = r["vertices"], r["faces"], r["albedo"], r["image"]
    assert v.ndim == 2 and v.shape[1] == 3 and a.shape == v.shape
    assert f.shape[1] == 3 and f.max() < len(v)
    assert img.shape == (64, 64, 4)
    rep = r["report"]
    # The default model is ICT-FaceKit's; exact landmarks get 3000 landmark steps.
    assert len(v) > 10000 and rep["target"] == "synthetic"
    assert rep["full_iterations"] == 2 and rep["iterations"] == rep["landmark_iterations"] + 2
    assert np.isfinite(r["report"]["landmark_error_px"])
    assert len(r["params"]["z_id"]) > 0 and len(r["params"]["sh"]) == 9


def test_fit_face_image_with_landmarks():
    # A synthetic face as a photo, its landmarks given: the in-memory target path.
    syn = tapestry.fit_face(iters=2, size=64, seed=2)
    img = np.clip(syn["image"][..., :3], 0, 1)
    with pytest.raises(ValueError, match="landmarks need an image"):
        tapestry.fit_face(landmarks=np.zeros((68, 2)), iters=2)
    with pytest.raises(TypeError, match="image: dtype float32"):
        tapestry.fit_face(img.astype(np.float32), iters=2)
    with pytest.raises(tapestry.TapestryError):
        tapestry.fit_face(img, np.zeros((5, 2)), iters=2, size=64)


def test_gradcheck_cases():
    recs, passed = tapestry.gradcheck("sh")
    assert passed and len(recs) > 0
    assert all(r["passed"] for r in recs) and {"op", "max_rel_err"} <= set(recs[0])
    with pytest.raises(tapestry.TapestryError, match="gradcheck: no op matches 'zzz'"):
        tapestry.gradcheck("zzz")


def test_gradcheck_scene():
    rep, passed = tapestry.gradcheck_scene(PEERS / "scenes" / "ico5k_hard.json", "colors",
                                           vertices=8)
    assert passed and isinstance(rep, dict)
