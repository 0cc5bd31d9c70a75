"""render_scene and grad_scene against the command line, bit for bit."""

import numpy as np
import pytest

import tapestry
from conftest import PEERS, reference_scenes


@pytest.mark.parametrize("scene", reference_scenes(), ids=lambda p: p.name)
def test_render_matches_cli_bit_for_bit(scene, cli, tmp_path):
    cli("render", scene, "--out", tmp_path / "a.png", "--npy", tmp_path / "a.npy")
    want = np.load(tmp_path / "a.npy")
    got = tapestry.render_scene(scene)
    assert got.dtype == np.float64 and want.dtype == np.float64
    assert got.shape == want.shape and got.shape[2] == 4
    assert np.array_equal(got, want)


def test_render_float32(tmp_path):
    scene = PEERS / "scenes" / "ico5k_hard.json"
    img32 = tapestry.render_scene(scene, dtype="float32")
    img64 = tapestry.render_scene(scene)
    assert img32.dtype == np.float32
    assert np.abs(img32.astype(np.float64) - img64).max() < 1e-4


def _target_for(scene, tmp_path):
    img = tapestry.render_scene(scene)
    # The scene's own image moved by one pixel: dL/dI is non-zero along edges.
    t = np.roll(img, (1, 1), axis=(0, 1))
    np.save(tmp_path / "target.npy", t)
    return t


@pytest.mark.parametrize("scene,wrt", [
    (PEERS / "scenes" / "ico5k_hard.json", "positions"),
    (PEERS / "scenes" / "ico5k_deodr.json", "positions"),
    (PEERS / "scenes" / "ico5k_hard.json", "colors"),
    (PEERS / "scenes" / "ico5k_hard.json", "camera"),
    (PEERS / "scenes" / "ico5k_deodr.json", "camera"),
], ids=lambda x: getattr(x, "name", x))
def test_grad_matches_cli_bit_for_bit(scene, wrt, cli, tmp_path):
    target = _target_for(scene, tmp_path)
    out = cli("grad", scene, "--target", tmp_path / "target.npy", "--wrt", wrt,
              "--out", tmp_path / "g.npy")
    want_loss = float(out.split()[1])
    want = np.load(tmp_path / "g.npy")
    loss, g = tapestry.grad_scene(scene, target, wrt=wrt)
    # The CLI prints the loss with 17 significant digits: exact for a float64.
    assert loss == want_loss
    assert g.shape == want.shape and g.dtype == want.dtype
    assert np.array_equal(g, want)
    # A path target is read as the command line reads it.
    loss2, g2 = tapestry.grad_scene(scene, tmp_path / "target.npy", wrt=wrt)
    assert loss2 == loss and np.array_equal(g2, g)


def test_grad_rgb_target_and_peer_target(cli, tmp_path):
    scene = PEERS / "scenes" / "ico5k_hard.json"
    target = np.load(PEERS / "reference" / "deodr_target.npy")
    out = cli("grad", scene, "--target", PEERS / "reference" / "deodr_target.npy",
              "--wrt", "colors", "--out", tmp_path / "g.npy")
    loss, g = tapestry.grad_scene(scene, target, wrt="colors")
    assert loss == float(out.split()[1])
    assert np.array_equal(g, np.load(tmp_path / "g.npy"))


@pytest.mark.parametrize("wrt", ["texture", "lights", "positions", "camera"])
def test_grad_textured_lit_scene_matches_cli(textured_scene, wrt, cli, tmp_path):
    target = _target_for(textured_scene, tmp_path)
    out = cli("grad", textured_scene, "--target", tmp_path / "target.npy", "--wrt", wrt,
              "--out", tmp_path / "g.npy")
    loss, g = tapestry.grad_scene(textured_scene, target, wrt=wrt)
    assert loss == float(out.split()[1])
    assert np.array_equal(g, np.load(tmp_path / "g.npy"))
    assert np.abs(g).max() > 0


def test_render_textured_scene_matches_cli(textured_scene, cli, tmp_path):
    cli("render", textured_scene, "--out", tmp_path / "a.png", "--npy", tmp_path / "a.npy")
    assert np.array_equal(tapestry.render_scene(textured_scene), np.load(tmp_path / "a.npy"))
