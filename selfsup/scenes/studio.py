"""Objects photographed in the dark: the real-photograph case, made by our own generator.

A photometric-stereo set (DiLiGenT and the like) shows one object of one albedo, often glossy,
lit by one small lamp far from it in a dark room, seen by a narrow-angle camera; there is no
room, so every pixel but the object's is black and has no depth. :func:`studio_spec` builds
such a scene for the exact renderer (:func:`selfsup.scenes.exact.render_spec`): a sphere and,
optionally, a box and a cylinder beside it, all of one albedo, before a black background,
with one light (or none, and a uniform ambient: the frame lit by diffuse light alone).
Camera frame (OpenCV: x right, y down, z forward), metres.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from selfsup.scenes.raycast import Primitives
from selfsup.scenes.sampler import Materials, SceneSpec, Texture

__all__ = ["studio_spec", "sphere_centre", "PATTERNS"]


# The paints of :func:`studio_spec`: one albedo, stripes of a second one (hard edges, as
# painted bands), or fractal noise between the two (an albedo that changes smoothly).
PATTERNS = {"uniform": Texture.UNIFORM, "stripes": Texture.STRIPES, "noise": Texture.NOISE}


def _materials(count: int, albedo: tuple[float, float, float], ks: float, shininess: float, pattern: str,
               second_albedo: tuple[float, float, float], pattern_scale: float,
               pattern_direction: tuple[float, float, float] = (0.6, 0.8, 0.0)) -> Materials:
    # ``count`` primitives of one paint (an albedo, or a pattern of it and ``second_albedo``)
    # and one gloss, float32 as the sampler's.
    kd = torch.tensor(albedo, dtype=torch.float32).expand(count, 3).clone()
    alt = torch.tensor(second_albedo, dtype=torch.float32).expand(count, 3).clone()
    direction = torch.tensor(pattern_direction, dtype=torch.float32)
    return Materials(kd_base=kd, kd_alt=alt, texture=torch.full((count,), PATTERNS[pattern], dtype=torch.long),
                     texture_scale=torch.full((count,), float(pattern_scale)),
                     texture_dir=(direction / direction.norm()).expand(count, 3).clone(),
                     ks=torch.full((count,), float(ks)), shininess=torch.full((count,), float(shininess)))


def studio_spec(light_direction: tuple[float, float, float] | None, *, width: int = 160, height: int = 120,
                fov_x_deg: float = 12.0, distance: float = 5.0, radius: float = 0.25, light_distance: float = 20.0,
                others: bool = True, albedo: tuple[float, float, float] = (0.8, 0.78, 0.75), ks: float = 0.3,
                shininess: float = 60.0, ambient: float = 0.0, exposure: float = 0.9, seed: int = 0,
                pattern: str = "uniform", second_albedo: tuple[float, float, float] | None = None,
                pattern_scale: float | None = None) -> SceneSpec:
    """A sphere of ``radius`` metres ``distance`` metres before the camera (and, with
    ``others``, a box and an upright cylinder beside it), of one ``albedo`` and gloss
    (``ks``, ``shininess``), against a black background, in a camera of ``fov_x_deg``.

    ``pattern``: the paint, :data:`PATTERNS`: ``uniform`` (``albedo``), ``stripes`` (bands of
    ``albedo`` and ``second_albedo``, ``pattern_scale`` metres a pair, default ``radius``;
    across the objects' surfaces, as stripes painted on a figure) or ``noise`` (fractal noise
    between the two: an albedo that changes smoothly). ``second_albedo`` defaults to 55% of
    ``albedo`` (a grey paint on a white one).

    ``light_direction``: unit direction from the sphere's centre to the one light (camera
    frame), which stands ``light_distance`` sphere radii away; None: no light, the scene
    lit by a uniform ``ambient`` alone (a frame of diffuse light). ``exposure``: the 99th
    percentile of the rendered image (the renderer's). The truth is the spec's light."""
    if not (0 < fov_x_deg < 180 and distance > radius > 0 and light_distance > 1 and width >= 8 and height >= 8):
        raise ValueError(f"studio_spec needs 0 < fov_x_deg < 180, distance > radius > 0, light_distance > 1 and an "
                         f"image of at least 8x8, got {fov_x_deg}, {distance}, {radius}, {light_distance}, "
                         f"{width}x{height}")
    if pattern not in PATTERNS:
        raise ValueError(f"pattern must be one of {sorted(PATTERNS)}, got {pattern!r}")
    if pattern_scale is not None and not pattern_scale > 0:
        raise ValueError(f"pattern_scale must be > 0 metres, got {pattern_scale}")
    focal = width / 2 / math.tan(math.radians(fov_x_deg) / 2)
    K = torch.tensor([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]], dtype=torch.float64)
    centre = torch.tensor([0.0, 0.0, distance], dtype=torch.float64)
    spheres = torch.cat([centre, torch.tensor([radius], dtype=torch.float64)])[None]
    boxes = torch.zeros(0, 15, dtype=torch.float64)
    cylinders = torch.zeros(0, 8, dtype=torch.float64)
    if others:
        # A box turned 30 degrees about the vertical, left of the sphere and a little behind it,
        # and an upright cylinder to its right, both resting at the sphere's lowest height.
        angle = math.radians(30.0)
        rotation = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]],
                                dtype=torch.float64)
        half = torch.tensor([0.7, 0.7, 0.7], dtype=torch.float64) * radius
        box_centre = centre + torch.tensor([-2.6 * radius, radius - half[1], 1.2 * radius], dtype=torch.float64)
        boxes = torch.cat([box_centre, half, rotation.reshape(-1)])[None]
        cylinders = torch.tensor([[2.5 * radius, 0.0, distance + 0.8 * radius, 0.0, 1.0, 0.0, 0.6 * radius, radius]],
                                 dtype=torch.float64)
    prims = Primitives(spheres=spheres, boxes=boxes, cylinders=cylinders)
    count = 1 + boxes.shape[0] + cylinders.shape[0]
    if light_direction is None:  # a light of no intensity above the camera: the renderer takes one light or more
        lights = (centre + torch.tensor([0.0, -light_distance * radius, 0.0], dtype=torch.float64))[None]
        intensity = torch.zeros(1, 3, dtype=torch.float64)
        ambient_rgb = torch.full((3,), max(float(ambient), 1e-3), dtype=torch.float64)
    else:
        direction = torch.tensor(light_direction, dtype=torch.float64)
        if not (bool(torch.isfinite(direction).all()) and float(direction.norm()) > 0):
            raise ValueError(f"light_direction must be a finite nonzero vector, got {light_direction}")
        lights = (centre + direction / direction.norm() * light_distance * radius)[None]
        intensity = torch.ones(1, 3, dtype=torch.float64) * (light_distance * radius) ** 2
        ambient_rgb = torch.full((3,), float(ambient), dtype=torch.float64)
    second = tuple(0.55 * a for a in albedo) if second_albedo is None else second_albedo
    paint = _materials(count, albedo, ks, shininess, pattern, second, radius if pattern_scale is None else pattern_scale)
    return SceneSpec(prims=prims.to(torch.float32), materials=paint, K=K.float(),
                     height=height, width=width, light_position=lights.float(),
                     light_relative_intensity=intensity.float(), ambient_relative=ambient_rgb.float(),
                     exposure=exposure, seed=seed, meta={"studio": True, "objects": count})


def sphere_centre(spec: SceneSpec) -> Tensor:
    """The sphere's centre ``(3,)`` of a :func:`studio_spec` (the point light directions are judged from)."""
    return spec.prims.spheres[0, :3]
