"""Exact ray caster: hits and normals on analytic primitives."""

import math

import torch

from selfsup.scenes.raycast import Primitives, any_hit, camera_rays, cast_rays


def test_box_hit_from_outside_and_inside():
    box = Primitives(boxes=torch.tensor([[0, 0, 5.0, 1, 1, 1, 1, 0, 0, 0, 1, 0, 0, 0, 1]], dtype=torch.float64))
    origins = torch.tensor([[0.0, 0, 0], [0.0, 0, 5.0]], dtype=torch.float64)
    dirs = torch.tensor([[0.0, 0, 1], [0.0, 0, 1]], dtype=torch.float64)
    hit = cast_rays(box, origins, dirs)
    torch.testing.assert_close(hit.t, torch.tensor([4.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(hit.normal, torch.tensor([[0.0, 0, -1], [0.0, 0, 1]], dtype=torch.float64))


def test_a_ray_along_a_plane_or_slab_changes_no_other_rays_hit():
    # Plane and box tests guard against rays with no component across a plane or slab
    # only in blocks that hold one; other rays must get the same t either way.
    prims = Primitives(planes=torch.tensor([[0, 1.0, 0, 0, -1, 0]]),
                       boxes=torch.tensor([[0.3, 0, 5.0, 1, 1, 1, 0.8, 0, 0.6, 0, 1, 0, -0.6, 0, 0.8]]),
                       cylinders=torch.tensor([[-1.5, 0, 4.0, 0, 1, 0, 0.3, 0.5]]))
    generic = torch.tensor([[0.05, 0.3, 1.0], [0.1, -0.02, 1.0], [0.02, 0.21, 1.0], [-0.375, 0.05, 1.0]])
    along = torch.tensor([[0.0, 0.0, 1.0], [-0.375, 0.0, 1.0]])  # along the plane y = 1, the box's y slab, the caps
    alone = cast_rays(prims, torch.zeros(4, 3), generic)
    mixed = cast_rays(prims, torch.zeros(6, 3), torch.cat([generic, along]))
    assert torch.equal(alone.t, mixed.t[:4]) and torch.equal(alone.primitive, mixed.primitive[:4])
    assert alone.primitive.tolist() == [0, 1, 1, 2]  # the floor, the box twice, the cylinder
    assert mixed.primitive[4:].tolist() == [1, 2]  # the box, the cylinder: not the plane they run along


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


def test_bundled_rays_give_what_every_ray_against_every_primitive_gives():
    # Rays from one origin are culled bundle by bundle; appending one ray from
    # elsewhere makes every ray meet every primitive. Both must agree, for coherent
    # (pixel-tile) and for shuffled bundles, for the nearest hit and for shadow rays.
    import dataclasses

    from selfsup.scenes.sampler import SamplerConfig, sample_scene

    spec = sample_scene(11, dataclasses.replace(SamplerConfig(), height=48, width=64))
    prims = spec.prims
    dirs = camera_rays(spec.K, 48, 64)
    for order in (torch.arange(len(dirs)), torch.randperm(len(dirs), generator=torch.Generator().manual_seed(0))):
        d = dirs[order]
        shared = cast_rays(prims, torch.zeros(1, 3).expand_as(d), d)
        every = cast_rays(prims, torch.cat([torch.zeros_like(d), torch.ones(1, 3)]), torch.cat([d, d[:1]]))
        assert torch.equal(shared.t, every.t[:-1])
        assert torch.equal(shared.primitive, every.primitive[:-1])
        torch.testing.assert_close(shared.normal, every.normal[:-1])
        light = spec.light_position[0]
        points = d * shared.t[:, None]
        end = torch.full((len(d),), 0.999)
        from_light = any_hit(prims, light.expand_as(points), points - light, 0.0, end)
        each = any_hit(prims, torch.cat([light.expand_as(points), torch.zeros(1, 3)]), torch.cat([points - light, d[:1]]),
                       0.0, torch.cat([end, end[:1]]))
        assert torch.equal(from_light, each[:-1])
        assert 0.0 < from_light.float().mean() < 0.9  # some points shadowed, most lit


def test_a_ray_without_direction_does_not_hide_its_bundles_hits():
    # A zero (or NaN) direction makes its bundle's cone NaN; the cone must then cover
    # everything rather than cull the bundle's other rays.
    sphere = Primitives(spheres=torch.tensor([[0, 0, 5.0, 1.0]]))
    d = torch.zeros(10, 3)
    d[:, 2] = 1
    d[0] = 0
    d[1] = float("nan")
    origins = torch.zeros(1, 3).expand(10, 3)
    assert torch.equal(cast_rays(sphere, origins, d).t[2:], torch.full((8,), 4.0))
    assert any_hit(sphere, origins, d, 0.0, torch.full((10,), 10.0))[2:].all()
