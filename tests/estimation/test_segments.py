"""Smooth-surface segmentation of a G-buffer (render.geometry.surface_segments)."""

import pytest
import torch

from selfsup.estimation.normals import surface_segments


def _two_walls_and_a_box():
    # 20 x 30 pixels: a wall facing the camera on the left, a side wall (normal 90 degrees
    # away) on the right at the same depth, a box face 1 m in front in the middle of the
    # left part, and a hole of missing depth in the bottom-right corner.
    H, W = 20, 30
    points = torch.zeros(1, H, W, 3)
    points[..., 2] = 3.0
    normals = torch.zeros(1, H, W, 3)
    normals[..., 2] = -1.0
    normals[:, :, 15:] = torch.tensor([-1.0, 0.0, 0.0])
    points[:, 5:12, 4:10, 2] = 2.0
    mask = torch.ones(1, H, W, dtype=torch.bool)
    mask[:, 16:, 25:] = False
    return points, normals, mask


def test_walls_box_and_hole_are_told_apart():
    points, normals, mask = _two_walls_and_a_box()
    label = surface_segments(points, normals, mask)[0]
    assert (label[~mask[0]] == -1).all()
    left = torch.ones_like(mask[0])
    left[:, 15:] = False
    left[5:12, 4:10] = False
    regions = [left, ~left & mask[0] & (torch.arange(30) >= 15), torch.zeros_like(left).index_put_(
        (torch.arange(5, 12)[:, None], torch.arange(4, 10)[None]), torch.tensor(True))]
    found = [label[r].unique() for r in regions]
    assert all(f.numel() == 1 for f in found), found  # each region one label ...
    assert len({int(f) for f in found}) == 3  # ... and a different one each


def test_a_curved_surface_stays_one_segment():
    # A cylinder seen from the side: normals turn 60 degrees across it, 3 degrees per pixel.
    angle = torch.linspace(-1.05, 1.05, 21)
    normals = torch.stack([torch.sin(angle), torch.zeros_like(angle), -torch.cos(angle)], -1).expand(1, 10, 21, 3)
    points = torch.zeros(1, 10, 21, 3)
    points[..., 2] = 2.0 - 0.3 * torch.cos(angle)
    label = surface_segments(points, normals.contiguous(), torch.ones(1, 10, 21, dtype=torch.bool))
    assert label.unique().numel() == 1


def test_shapes_are_checked():
    points, normals, mask = _two_walls_and_a_box()
    with pytest.raises(ValueError, match="must be"):
        surface_segments(points, normals, mask[0])


def _joined(log_grey, chroma=None, labels=None, surfaces=None, max_step=0.05, max_chroma=0.03):
    import numpy as np

    from selfsup.estimation.albedo_free.regions import join_shading_cuts

    H, W = log_grey.shape
    chroma = np.zeros((H, W, 2)) if chroma is None else chroma
    labels = (np.arange(W)[None] // 4).repeat(H, 0) if labels is None else labels  # bands 4 px wide: cut every 4 px
    surfaces = np.zeros((H, W), dtype=np.int64) if surfaces is None else surfaces
    return join_shading_cuts(labels, log_grey, chroma, np.zeros((H, W)), surfaces, max_step, max_chroma)


def test_cuts_across_smooth_shading_are_joined_and_albedo_edges_are_kept():
    import numpy as np

    H, W = 12, 32
    x = np.arange(W)[None].repeat(H, 0).astype(float)
    ramp = np.log(0.2 + 0.8 * np.cos(np.radians(80) * x / W) ** 2)  # a falloff steepening along the rows
    assert (_joined(ramp) == 0).all()  # one region: every cut is shading
    step = ramp + np.where(x >= 16, np.log(0.6), 0.0)  # an albedo 0.6 times as bright from column 16
    joined = _joined(step)
    assert len(np.unique(joined[:, :16])) == 1 and len(np.unique(joined[:, 16:])) == 1 and joined[0, 0] != joined[0, -1]
    chroma = np.zeros((H, W, 2))
    chroma[:, 16:, 0] = 0.2  # the same brightness, another hue (red more than green)
    coloured = _joined(ramp, chroma)
    assert coloured[0, 0] != coloured[0, -1] and len(np.unique(coloured)) == 2
    surfaces = (x >= 16).astype(np.int64)  # two smooth surfaces never join, whatever their shading
    assert len(np.unique(_joined(ramp, surfaces=surfaces))) == 2
    assert (_joined(ramp, labels=np.where(x < 2, -1, x // 4).astype(np.int64))[:, :2] == -1).all()
