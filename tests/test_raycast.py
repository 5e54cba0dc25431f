"""Exact ray caster: hits and normals on analytic primitives."""

import math

import torch

from selfsup.scenes.raycast import Primitives, cast_rays


def test_box_hit_from_outside_and_inside():
    box = Primitives(boxes=torch.tensor([[0, 0, 5.0, 1, 1, 1, 1, 0, 0, 0, 1, 0, 0, 0, 1]], dtype=torch.float64))
    origins = torch.tensor([[0.0, 0, 0], [0.0, 0, 5.0]], dtype=torch.float64)
    dirs = torch.tensor([[0.0, 0, 1], [0.0, 0, 1]], dtype=torch.float64)
    hit = cast_rays(box, origins, dirs)
    torch.testing.assert_close(hit.t, torch.tensor([4.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(hit.normal, torch.tensor([[0.0, 0, -1], [0.0, 0, 1]], dtype=torch.float64))


def test_sphere_plane_cylinder_hits():
    prims = Primitives(
        planes=torch.tensor([[0, 1.0, 0, 0, -1, 0]], dtype=torch.float64),
        spheres=torch.tensor([[0, 0, 4.0, 1.0]], dtype=torch.float64),
        cylinders=torch.tensor([[3.0, 0, 4.0, 0, 1, 0, 0.5, 0.5]], dtype=torch.float64),
    )
    o = torch.zeros(3, 3, dtype=torch.float64)
    d = torch.tensor([[0, 0, 1.0], [0, 1.0, 1.0], [3.0, 0, 4.0]], dtype=torch.float64)
    hit = cast_rays(prims, o, d)
    torch.testing.assert_close(hit.t[0], torch.tensor(3.0, dtype=torch.float64))  # sphere front
    torch.testing.assert_close(hit.t[1], torch.tensor(1.0, dtype=torch.float64))  # floor y = 1
    torch.testing.assert_close(hit.t[2], torch.tensor(1 - 0.5 / 5, dtype=torch.float64))  # cylinder side
    torch.testing.assert_close(hit.normal[2], torch.tensor([-0.6, 0, -0.8], dtype=torch.float64))
    # Large batches stay linear in memory.
    many = cast_rays(prims, torch.zeros(70000, 3, dtype=torch.float64), d[:1].expand(70000, 3))
    assert math.isclose(many.t.max().item(), 3.0)
