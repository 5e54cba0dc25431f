import math

import pytest
import torch

from render.types import GBuffer
from selfsup.scenes.exact import render_spec
from selfsup.scenes.integration import integrated_depth
from selfsup.scenes.studio import photograph, studio_spec

LAMP = (0.3, -0.5, -0.81)


def _depth_normal_error_deg(depth, scene):
    # Median angle between the normals of ``depth`` and the render's true normals, where both exist.
    g = GBuffer.from_depth(depth[None], scene.K[None])
    valid = g.mask[0] & (scene.depth > 0)
    cosine = (g.normals[0] * scene.normals).sum(-1).clamp(-1, 1)[valid]
    return math.degrees(float(cosine.acos().median()))


def test_a_smooth_objects_integrated_depth_is_its_depth():
    scene = render_spec(studio_spec(LAMP, others=False)).scene
    depth = integrated_depth(scene.normals, scene.depth, scene.K)
    inside = scene.depth > 0
    assert bool((depth[inside] > 0).all()) and bool((depth[~inside] == 0).all())
    assert float((depth - scene.depth)[inside].abs().median()) < 1e-3  # metres: 0.36 mm (2026-12-07)
    assert _depth_normal_error_deg(depth, scene) < 0.5


def test_parts_that_hide_each_other_integrate_to_one_tilted_sheet():
    # The box half in front of the sphere, the cylinder half behind it: one region, and no normal
    # says how far the hidden parts jump, so the least squares tilt both (as DiLiGenT's figures).
    apart = render_spec(studio_spec(LAMP, arrangement="apart")).scene
    overlapping = render_spec(studio_spec(LAMP, arrangement="overlapping")).scene
    assert _depth_normal_error_deg(integrated_depth(apart.normals, apart.depth, apart.K), apart) < 0.5
    sheet = integrated_depth(overlapping.normals, overlapping.depth, overlapping.K)
    inside = overlapping.depth > 0
    assert float((sheet - overlapping.depth)[inside].abs().median()) > 0.03  # 0.086 m (2026-12-07)
    assert _depth_normal_error_deg(sheet, overlapping) > 2.0  # 4.2 degrees


def test_integrated_depth_is_checked():
    scene = render_spec(studio_spec(LAMP, others=False, width=16, height=12)).scene
    with pytest.raises(ValueError, match=r"normals \(H, W, 3\)"):
        integrated_depth(scene.normals[..., :2], scene.depth, scene.K)
    with pytest.raises(ValueError, match="finite"):
        integrated_depth(torch.full_like(scene.normals, math.nan), scene.depth, scene.K)
    assert bool((integrated_depth(scene.normals, torch.zeros_like(scene.depth), scene.K) == 0).all())
    with pytest.raises(ValueError, match="arrangement"):
        studio_spec(LAMP, arrangement="stacked")
    with pytest.raises(ValueError, match="depth must be"):
        photograph("unused", studio_spec(LAMP, others=False), depth="sensor")
