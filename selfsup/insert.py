"""Virtual object insertion by differential rendering (Debevec 1998).

A sphere is added to the scene's geometry; the scene is rendered with and
without it under the estimated lights, and the difference (the object's shading
where it is, its cast shadow and the light it blocks elsewhere) is added to the
real image. Where the estimated lights are wrong, the inserted shadow disagrees
with the real ones: this is the picture users judge an estimate by.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from render import GBuffer, Material, PointLights, render_image
from selfsup.scenes.io import Scene, render_inputs

__all__ = ["Sphere", "default_sphere", "insert_sphere", "lights_from_record", "insert_files"]


@dataclass
class Sphere:
    """``centre (3,)`` camera-frame metres, ``radius`` metres, diffuse ``albedo (3,)``,
    specular ``ks`` and ``shininess``."""

    centre: Tensor
    radius: float
    albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
    ks: float = 0.2
    shininess: float = 40.0

    def __post_init__(self):
        if not self.radius > 0 or not bool(torch.isfinite(self.centre).all()):
            raise ValueError(f"sphere needs a finite centre and a radius > 0, got {self.centre.tolist()}, {self.radius}")


def default_sphere(gbuffer: GBuffer, pixel: tuple[float, float] = (0.5, 0.7), size: float = 0.05) -> Sphere:
    """A sphere resting on the upward-facing surface (normal within 45 degrees of the
    camera's up, -y) nearest to ``pixel`` (fractions of width, height), or on any
    surface when none faces up; its radius ``size`` times the valid points'
    bounding-box diagonal."""
    mask = gbuffer.mask[0]
    if not bool(mask.any()):
        raise ValueError("the scene has no valid pixel to put an object on")
    H, W = mask.shape
    upward = mask & (-gbuffer.normals[0, ..., 1] > 0.7)
    v, u = torch.nonzero(upward if bool(upward.any()) else mask, as_tuple=True)
    target = torch.tensor([pixel[1] * (H - 1), pixel[0] * (W - 1)])
    nearest = ((v - target[0]) ** 2 + (u - target[1]) ** 2).argmin()
    point = gbuffer.points[0, v[nearest], u[nearest]]
    normal = gbuffer.normals[0, v[nearest], u[nearest]]
    valid = gbuffer.points[0][mask]
    radius = size * float((valid.amax(0) - valid.amin(0)).norm())
    return Sphere(centre=point + radius * normal, radius=radius)


def _sphere_hits(K: Tensor, H: int, W: int, sphere: Sphere) -> tuple[Tensor, Tensor]:
    # Depth (z) of the first ray-sphere hit per pixel (inf for none) and the unit normals (H, W, 3).
    v, u = torch.meshgrid(torch.arange(H, dtype=K.dtype), torch.arange(W, dtype=K.dtype), indexing="ij")
    rays = torch.stack([u, v, torch.ones_like(u)], -1) @ torch.linalg.inv(K).T  # z = 1
    c = sphere.centre.to(K.dtype)
    a = (rays * rays).sum(-1)
    b = (rays * c).sum(-1)
    disc = b * b - a * ((c * c).sum() - sphere.radius**2)
    t = (b - disc.clamp_min(0).sqrt()) / a
    hit = (disc > 0) & (t > 0)
    depth = torch.where(hit, t, torch.full_like(t, float("inf")))
    normals = (rays * t[..., None] - c) / sphere.radius
    return depth, normals


def lights_from_record(record: dict) -> tuple[Tensor, Tensor, Tensor]:
    """``(positions (L, 3), intensities (L, 3), ambient (3,))`` of an estimate's JSON record."""
    try:
        position = torch.tensor([light["position"] for light in record["lights"]], dtype=torch.float32)
        intensity = torch.tensor([light["intensity"] for light in record["lights"]], dtype=torch.float32)
        ambient = torch.tensor(record.get("ambient", [0.0, 0.0, 0.0]), dtype=torch.float32)
    except (KeyError, TypeError) as error:
        raise ValueError(f"estimate record {record.get('id', '?')} lacks lights/position/intensity: {error}") from None
    return position.reshape(-1, 3), intensity.reshape(-1, 3), ambient


def insert_sphere(scene: Scene, position: Tensor, intensity: Tensor, ambient: Tensor, sphere: Sphere,
                  shadows: str = "epipolar") -> tuple[Tensor, Tensor]:
    """The scene's image ``(H, W, 3)`` with ``sphere`` inserted under the given lights
    (``(L, 3)`` positions and intensities, ambient ``(3,)``), and the object's mask ``(H, W)``."""
    gbuffer, material, _ = render_inputs(scene)
    H, W = scene.depth.shape
    depth, normals = _sphere_hits(scene.K, H, W, sphere)
    scene_depth = torch.where(gbuffer.mask[0], scene.depth, torch.full_like(scene.depth, float("inf")))
    on_object = depth < scene_depth
    with_depth = torch.where(on_object, depth, scene.depth)
    with_normals = torch.where(on_object[..., None], normals, gbuffer.normals[0])
    g_with = GBuffer.from_depth(torch.where(torch.isfinite(with_depth), with_depth, torch.zeros_like(with_depth))[None],
                                scene.K[None], with_normals[None])
    albedo = torch.tensor(sphere.albedo, dtype=scene.kd.dtype)
    kd = torch.where(on_object[..., None], albedo, scene.kd)[None]
    ks_scene = material.ks if material.ks is not None else torch.zeros(1, H, W, 1)
    ks = torch.where(on_object[None, ..., None], torch.full_like(ks_scene, sphere.ks), ks_scene)
    shininess = torch.as_tensor(material.shininess, dtype=kd.dtype).expand(1, H, W)
    shininess = torch.where(on_object[None], torch.tensor(sphere.shininess, dtype=kd.dtype), shininess)
    m_with = Material(kd=kd, ks=ks, shininess=shininess)
    m_without = Material(kd=material.kd, ks=ks_scene, shininess=shininess)
    lights = PointLights(position=position[None].to(kd.dtype), intensity=intensity[None].to(kd.dtype))
    options = dict(falloff=scene.falloff, shadows=shadows)
    with torch.no_grad():
        rendered_with = render_image(g_with, m_with, lights, ambient[None].to(kd.dtype), **options)[0].permute(1, 2, 0)
        rendered_without = render_image(gbuffer, m_without, lights, ambient[None].to(kd.dtype), **options)[0].permute(1, 2, 0)
    real = torch.where(torch.isfinite(scene.image), scene.image, torch.zeros_like(scene.image))
    composite = torch.where(on_object[..., None], rendered_with, (real + rendered_with - rendered_without).clamp_min(0))
    return composite, on_object


def insert_files(scene: str, output: str, estimates: str | None = None, size: float = 0.05,
                 pixel: tuple[float, float] = (0.5, 0.7), shadows: str = "epipolar") -> Path:
    """Write ``output`` (PNG): the real image, the sphere inserted under the estimated
    lights (from ``estimates``, a JSON Lines file of ``mode=estimate``, or estimated
    now with the default method when None) and, when the file has them, under the true lights."""
    from skimage.io import imsave

    from selfsup.estimate import EstimateOptions, estimate_scene
    from selfsup.model import scene_frame
    from selfsup.scenes.generate import to_rgb8
    from selfsup.scenes.io import read_scene

    scene = read_scene(scene)
    if estimates is None:
        with torch.no_grad():
            record = estimate_scene(scene, EstimateOptions())
    else:
        records = [json.loads(line) for line in Path(estimates).read_text().splitlines() if line.strip()]
        matching = [r for r in records if r.get("id") == scene.id]
        if not matching:
            raise ValueError(f"{estimates} has no estimate for scene id {scene.id!r}")
        record = matching[0]
    gbuffer, _, _ = render_inputs(scene)
    sphere = default_sphere(gbuffer, tuple(pixel), size)
    panels = [scene.image]
    estimated, _ = insert_sphere(scene, *lights_from_record(record), sphere, shadows)
    panels.append(estimated)
    if scene.light_pos is not None:
        ambient = scene.ambient if scene.ambient is not None else torch.zeros(3)
        truth, _ = insert_sphere(scene, scene.light_pos, scene.light_intensity, ambient, sphere, shadows)
        panels.append(truth)
    exposure = scene_frame(scene.image.permute(2, 0, 1)[None], gbuffer).exposure[0]
    gap = np.full((scene.image.shape[0], 4, 3), 255, np.uint8)
    row = [part for panel in panels for part in (to_rgb8((panel / exposure).clamp(0, 1) ** (1 / 2.2)), gap)][:-1]
    path = Path(output)
    path.parent.mkdir(parents=True, exist_ok=True)
    imsave(str(path), np.concatenate(row, 1), check_contrast=False)
    return path
