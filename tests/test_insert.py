"""Virtual object insertion by differential rendering (mode=insert)."""

import dataclasses
import json

import pytest
import torch

from selfsup.insert import Mesh, Sphere, default_sphere, insert_object, insert_sphere, lights_from_record, load_obj, place_object
from selfsup.scenes.exact import render_spec
from selfsup.scenes.io import render_inputs, write_scene
from selfsup.scenes.sampler import SamplerConfig, sample_scene
from train import run
from tests.test_train import _cfg

SMALL = SamplerConfig(height=48, width=64, specular_prob=0.0)


@pytest.fixture(scope="module")
def scene():
    return render_spec(sample_scene(3, SMALL, n_lights=1), samples=1).scene


def test_insertion_changes_only_the_object_and_its_shadow(scene):
    gbuffer, _, _ = render_inputs(scene)
    sphere = default_sphere(gbuffer)
    ambient = scene.ambient if scene.ambient is not None else torch.zeros(3)
    composite, on_object = insert_sphere(scene, scene.light_pos, scene.light_intensity, ambient, sphere)
    assert composite.shape == scene.image.shape and torch.isfinite(composite).all()
    assert 0 < int(on_object.sum()) < on_object.numel() // 4
    changed = ((composite - scene.image).abs().amax(-1) > 1e-4) & ~on_object
    darker = ((composite - scene.image).sum(-1) < -1e-4) & ~on_object
    assert int(changed.sum()) < 0.5 * int((~on_object).sum())  # the rest of the picture is the real image
    assert int(darker.sum()) > 0  # the sphere casts a shadow on the real geometry


@pytest.mark.parametrize("shape", ["cube", "obj"])
def test_mesh_insertion_changes_only_the_object_and_its_shadow(scene, shape, tmp_path):
    if shape == "obj":  # a square pyramid: four triangles and a quad base
        (tmp_path / "p.obj").write_text("v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nv 0 2 0\n"
                                        "f 1 2 5\nf 2 3 5\nf 3 4 5\nf 4 1 5\nf 1/1 4/4 3/3 2/2\n")
        mesh = load_obj(tmp_path / "p.obj")
        assert mesh.faces.shape == (6, 3)
    else:
        mesh = Mesh.cube()
    gbuffer, _, _ = render_inputs(scene)
    placed = place_object(gbuffer, mesh, size=0.03)
    ambient = scene.ambient if scene.ambient is not None else torch.zeros(3)
    composite, on_object = insert_object(scene, scene.light_pos, scene.light_intensity, ambient, placed)
    assert torch.isfinite(composite).all() and 0 < int(on_object.sum()) < on_object.numel() // 4
    changed = ((composite - scene.image).abs().amax(-1) > 1e-4) & ~on_object
    darker = ((composite - scene.image).sum(-1) < -1e-4) & ~on_object
    assert int(changed.sum()) < 0.5 * int((~on_object).sum()) and int(darker.sum()) > 0


def test_cube_hits_match_the_analytic_front_face():
    # A unit cube 3 m ahead: the centre pixel sees its front face at z = 2.5, normal -z.
    K = torch.tensor([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]])
    cube = dataclasses.replace(Mesh.cube(), vertices=Mesh.cube().vertices * 0.5 + torch.tensor([0.0, 0.0, 3.0]))
    depth, normals = cube.hits(K, 25, 33)
    assert float(depth[12, 16]) == pytest.approx(2.5, abs=1e-5)
    assert torch.allclose(normals[12, 16], torch.tensor([0.0, 0.0, -1.0]))
    half_width_px = 50.0 * 0.5 / 2.5  # 10 px either side of the centre column
    row = torch.isfinite(depth[12])
    assert int(row.sum()) == pytest.approx(2 * half_width_px + 1, abs=1)
    assert not torch.isfinite(depth[0, 0])


def test_bad_meshes_are_named(tmp_path):
    (tmp_path / "empty.obj").write_text("# nothing\n")
    with pytest.raises(ValueError, match="has no triangles"):
        load_obj(tmp_path / "empty.obj")
    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 1 x 0\n")
    with pytest.raises(ValueError, match="bad.obj:2: cannot read"):
        load_obj(tmp_path / "bad.obj")
    with pytest.raises(ValueError, match="faces index vertices outside"):
        Mesh(torch.zeros(3, 3), torch.tensor([[0, 1, 3]]))
    with pytest.raises(ValueError, match="insert.object must be sphere, cube or an .obj file"):
        run(_cfg("mode=insert", "insert.scene=x.npz", "insert.output=x.png", "insert.object=teapot"))


def test_sphere_sits_on_an_upward_surface(scene):
    gbuffer, _, _ = render_inputs(scene)
    sphere = default_sphere(gbuffer, size=0.05)
    valid = gbuffer.points[0][gbuffer.mask[0]]
    assert sphere.radius == pytest.approx(0.05 * float((valid.amax(0) - valid.amin(0)).norm()))
    # The centre is one radius above a visible point, towards the camera's up (-y).
    nearest = (valid - sphere.centre).norm(dim=-1).min()
    assert float(nearest) == pytest.approx(sphere.radius, rel=0.05)


@pytest.mark.parametrize("pixel, size, message", [
    ((1.5, 0.5), 0.05, "insert.pixel must be two fractions"),
    ((0.5,), 0.05, "insert.pixel must be two fractions"),
    ((0.5, 0.7), -1.0, "insert.size must be > 0"),
    ((0.5, 0.7), float("nan"), "insert.size must be > 0"),
])
def test_bad_placements_are_named(scene, pixel, size, message):
    gbuffer, _, _ = render_inputs(scene)
    with pytest.raises(ValueError, match=message):
        place_object(gbuffer, Sphere(centre=torch.zeros(3), radius=1.0), pixel, size)


def test_bad_estimate_record_is_named():
    with pytest.raises(ValueError, match="scene_9 lacks lights"):
        lights_from_record({"id": "scene_9", "lights": [{"intensity": [1, 1, 1]}]})
    # A record from another tool: three lights of two coordinates were read as two lights of three.
    light = {"position": [1.0, 2.0, 3.0], "intensity": [1.0, 1.0, 1.0]}
    for bad, message in (({"lights": [{**light, "position": [1.0, 2.0]}] * 3}, "positions must be three"),
                         ({"lights": [{**light, "intensity": [1.0, float("nan"), 1.0]}]}, "intensities must be three"),
                         ({"lights": [light], "ambient": [0.1]}, "ambient must be three"),
                         ({"lights": [light, {**light, "position": [1.0]}]}, "ragged")):
        with pytest.raises(ValueError, match=message):
            lights_from_record({"id": "x", **bad})
    position, intensity, ambient = lights_from_record({"id": "x", "lights": []})
    assert position.shape == intensity.shape == (0, 3) and ambient.shape == (3,)


def test_insert_mode_writes_a_picture(tmp_path, scene):
    write_scene(tmp_path / "s.npz", scene)
    record = {"id": scene.id, "ambient": [0.0, 0.0, 0.0],
              "lights": [{"position": scene.light_pos[0].tolist(), "intensity": scene.light_intensity[0].tolist()}]}
    (tmp_path / "e.jsonl").write_text(json.dumps(record) + "\n")
    path = run(_cfg("mode=insert", f"insert.scene={tmp_path}/s.npz", f"insert.estimates={tmp_path}/e.jsonl",
                    f"insert.output={tmp_path}/out/i.png"))
    from skimage.io import imread

    picture = imread(path)
    assert picture.shape == (48, 3 * 64 + 2 * 4, 3)  # real | estimated | true
    (tmp_path / "other.jsonl").write_text(json.dumps(dict(record, id="other")) + "\n")
    with pytest.raises(ValueError, match="no estimate for scene id"):
        run(_cfg("mode=insert", f"insert.scene={tmp_path}/s.npz", f"insert.estimates={tmp_path}/other.jsonl",
                 f"insert.output={tmp_path}/x.png"))


def test_a_shadow_from_a_capture_estimate_darkens_the_surface_without_changing_its_colour(scene):
    # A capture's record gives every light and the ambient one (neutral) colour: the inserted
    # shadow scales each channel alike, so a wooden table stays wood-coloured, where a blue
    # ambient beside a white light painted it blue.
    from selfsup.estimation import EstimateOptions, estimate_scene

    capture = dataclasses.replace(scene, kd=torch.where(scene.depth[..., None] > 0, torch.full_like(scene.kd, 0.5), 0.0),
                                  ks=None, ambient=None)
    record = estimate_scene(capture, EstimateOptions(max_lights=1))
    position, intensity, ambient = lights_from_record(record)
    assert record["light_found"] and float(ambient.max() - ambient.min()) <= 1e-6 * float(ambient.max() + 1e-12)
    gbuffer, _, _ = render_inputs(scene)
    composite, on_object = insert_sphere(scene, position, intensity, ambient, default_sphere(gbuffer))
    shadow = (~on_object) & ((composite - scene.image).sum(-1) < -1e-3) & (scene.image.amin(-1) > 1e-3)
    assert int(shadow.sum()) > 0
    ratio = composite[shadow] / scene.image[shadow]  # (N, 3): the darkening of each channel
    assert torch.allclose(ratio, ratio.mean(-1, keepdim=True).expand_as(ratio), atol=1e-4)
