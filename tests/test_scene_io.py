"""Scene files: the format contract, round trips, and every bad-input case."""

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.devset_render import run as run_devset
from selfsup.scenes.io import Scene, SceneFileError, read_scene, render_inputs, write_scene

DEVSET = Path(__file__).resolve().parents[2] / "shared" / "devset"


def _scene(H=6, W=8):
    depth = torch.full((H, W), 2.0)
    return Scene(
        image=torch.rand(H, W, 3), depth=depth, K=torch.tensor([[8.0, 0, 3.5], [0, 8.0, 2.5], [0, 0, 1]]),
        kd=torch.rand(H, W, 3), meta={"id": "tiny", "generator": "test", "falloff": "inverse_square"},
        ks=torch.rand(H, W, 1), shininess=torch.full((H, W), 20.0), ambient=torch.full((3,), 0.1),
        light_pos=torch.tensor([[0.0, -1.0, 1.0]]), light_intensity=torch.ones(1, 3), scene_scale=torch.tensor(3.0),
    )


def test_round_trip(tmp_path):
    scene = _scene()
    write_scene(tmp_path / "s.npz", scene)
    back = read_scene(tmp_path / "s.npz")
    assert back.id == "tiny" and back.falloff == "inverse_square"
    for key in ("image", "depth", "K", "kd", "ks", "shininess", "ambient", "light_pos", "light_intensity",
                "scene_scale"):
        torch.testing.assert_close(getattr(back, key), getattr(scene, key))
    assert np.load(tmp_path / "s.npz")["image"].dtype == np.float32  # plain numpy reads it


def test_scalar_fields_stay_scalars(tmp_path):
    # The format allows shininess of shape (); a reader that made it (1,) gave a
    # Material that rejected every such file.
    path = _write_raw(tmp_path / "s.npz", shininess=np.array(20.0, np.float32))
    scene = read_scene(path)
    assert scene.shininess.shape == () and scene.scene_scale.shape == ()
    assert render_inputs(scene)[1].shininess.shape == ()


def test_a_subsampled_scene_keeps_the_points_of_the_pixels_it_keeps():
    H, W = 7, 9
    scene = _scene(H, W)
    scene.depth = 1.5 + torch.rand(H, W)
    scene.K = torch.tensor([[9.0, 0.0, 4.2], [0, 8.0, 3.1], [0, 0, 1]])
    scene.normals = torch.nn.functional.normalize(torch.randn(H, W, 3), dim=-1)
    sub = scene.subsampled(3)
    assert sub.image.shape == (3, 3, 3) and sub.shininess.shape == (3, 3) and sub.ambient.shape == (3,)
    points = render_inputs(scene)[0].points[0, ::3, ::3]
    torch.testing.assert_close(render_inputs(sub)[0].points[0], points)
    torch.testing.assert_close(sub.normals, scene.normals[::3, ::3])
    assert scene.subsampled(1) is scene and torch.equal(sub.light_pos, scene.light_pos)
    with pytest.raises(ValueError, match="stride must be an integer >= 1"):
        scene.subsampled(0)


def test_render_inputs_read_normals_as_the_format_says():
    # The estimator and the renderer's inputs (mode=insert, devset_render) share the
    # rules: missing normals from the depth, the other sign convention turned round.
    scene = _scene()
    scene.normals = torch.zeros(6, 8, 3)
    scene.normals[..., 2] = -1.0  # facing the camera (a plane at z = 2)
    given = render_inputs(scene)[0]
    scene.normals = -scene.normals
    scene.normals[0, 0] = 0
    turned = render_inputs(scene)[0]
    assert bool(turned.mask.all())
    torch.testing.assert_close(turned.normals, given.normals)


def _write_raw(path, **arrays):
    base = {k: v.numpy() for k, v in vars(_scene()).items() if isinstance(v, torch.Tensor)}
    base["meta"] = np.array('{"id": "x"}')
    base.update(arrays)
    np.savez(path, **{k: v for k, v in base.items() if v is not None})
    return path


@pytest.mark.parametrize(
    "change,reason",
    [
        ({"image": None}, "missing key(s) image"),
        ({"kd": np.zeros((6, 8, 2), np.float32)}, "kd must have shape"),
        ({"image": np.full((6, 8, 3), np.nan, np.float32)}, "image holds non-finite"),
        ({"image": -np.ones((6, 8, 3), np.float32)}, "negative"),
        ({"depth": np.zeros((6, 8), np.float32)}, "empty valid mask"),
        ({"light_intensity": None}, "light_pos and light_intensity"),
        ({"shininess": np.zeros((6, 8), np.float32)}, "shininess must be > 0"),
        ({"meta": np.array("{not json")}, "meta is not JSON"),
        ({"K": np.zeros((3, 3), np.float32)}, "K must be pinhole intrinsics"),
        ({"kd": -np.ones((6, 8, 3), np.float32)}, "kd holds negative values"),
        ({"ambient": np.array([0.1, -0.1, 0.0], np.float32)}, "ambient holds negative values"),
        ({"K": np.diag([8.0, -8.0, 1.0]).astype(np.float32)}, "with fx, fy > 0"),
        ({"K": np.array([[8.0, 0.5, 3.5], [0, 8.0, 2.5], [0, 0, 1]], np.float32)}, "intrinsics with skew are not supported"),
        ({"meta": np.array('{"falloff": "linear"}')}, "meta.falloff must be one of ['inverse_square', 'none'], got 'linear'"),
        # A capture's raw integers, read as numbers, were silently wrong (sRGB read as linear,
        # lights in millimetres).
        ({"image": np.full((6, 8, 3), 128, np.uint8)}, "image must be floating point, got uint8 (8-bit images"),
        ({"depth": np.full((6, 8), 2000, np.uint16)}, "depth must be floating point, got uint16 (16-bit depth"),
        ({"K": np.array([["a"] * 3] * 3)}, "K must be numbers"),
    ],
)
def test_bad_files_name_file_and_reason(tmp_path, change, reason):
    path = _write_raw(tmp_path / "bad.npz", **change)
    with pytest.raises(SceneFileError, match=re.escape(reason)) as info:
        read_scene(path)
    assert "bad.npz" in str(info.value)


def test_albedo_above_one_and_depth_in_millimetres_are_read_with_a_warning(tmp_path, caplog):
    # Percent albedo scales the intensities by 100 and leaves the positions: a warning, not an error.
    base = _scene()
    with caplog.at_level("WARNING"):
        scene = read_scene(_write_raw(tmp_path / "percent.npz", kd=base.kd.numpy() * 100))
    assert torch.allclose(scene.kd, base.kd * 100) and "kd reaches" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING"):  # depth in millimetres, likewise
        read_scene(_write_raw(tmp_path / "mm.npz", depth=base.depth.numpy() * 1000))
    assert "median depth is" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING"):
        read_scene(_write_raw(tmp_path / "unit.npz"))
    assert "kd reaches" not in caplog.text and "median depth" not in caplog.text


def test_integer_intrinsics_and_shininess_are_read(tmp_path):
    # Exact in integers, unlike an image's or a depth map's units.
    K = np.array([[8, 0, 3], [0, 8, 2], [0, 0, 1]])
    scene = read_scene(_write_raw(tmp_path / "ints.npz", K=K, shininess=np.array(32)))
    assert scene.K.dtype == torch.float32 and float(scene.shininess) == 32.0


def test_unreadable_file(tmp_path):
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(SceneFileError, match="cannot read"):
        read_scene(tmp_path / "junk.npz")


@pytest.mark.skipif(not DEVSET.exists(), reason="shared/devset not present")
def test_devset_direct_scenes_render_like_the_independent_renderer():
    # Mitsuba's direct-light images against ours with the true lights: the
    # conventions (frame, falloff, I = P / pi) must agree on most pixels.
    rows, _ = run_devset(DEVSET, write=False)
    for row in rows:
        for method in ("none", "paper", "epipolar"):
            assert row[f"{method}_median_error"] < 0.02, (row["scene"], method)
