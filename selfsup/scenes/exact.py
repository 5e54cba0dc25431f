"""Exact ground-truth rendering of a sampled scene by batched ray casting.

Primary rays through pixels, exact shadow rays against the primitives (never the
shadow maps of ``render/``), the Blinn-Phong model of ``../shared/scene-format.md``
with inverse-square falloff by default, and ``samples x samples`` supersampled
anti-aliasing of the image. The stored G-buffer is that of the pixel centre ray
(depth, normals, ks, shininess) and the pixel-averaged albedo, as an RGB-D
sensor with an albedo estimate would give it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from selfsup.scenes.io import Scene
from selfsup.scenes.raycast import Primitives, any_hit, camera_rays, cast_rays, shade_exact
from selfsup.scenes.sampler import SceneSpec, Texture

__all__ = ["RenderedScene", "render_spec", "albedo_at", "fractal_noise"]

GENERATOR_NAME = "shadowlight.procedural v1 (exact ray casting)"


@dataclass
class RenderedScene:
    """A rendered spec: the ground-truth ``scene`` (scene-file contents, exact
    inputs) and the centre-ray cast-shadow ``visibility (H, W, L)`` (1 lit)."""

    scene: Scene
    visibility: Tensor


# Fixed wave directions and phases of the fractal pattern (a constant table, so
# scenes stay reproducible without any generator state).
_WAVES = torch.tensor([
    [0.57, 0.21, -0.79, 0.3], [-0.33, 0.88, 0.34, 1.7], [0.81, -0.45, 0.37, 2.9], [0.12, 0.64, 0.76, 4.1],
    [-0.71, -0.18, 0.68, 5.3], [0.42, 0.83, -0.37, 0.9], [0.93, 0.05, 0.36, 2.2], [-0.26, -0.61, -0.75, 3.6],
])


def fractal_noise(points: Tensor, scale: Tensor, octaves: int = 4) -> Tensor:
    """Smooth fractal pattern in [0, 1] at ``points (N, 3)`` with feature size ``scale (N,)``.

    A sum of plane waves in fixed directions, two per octave, the amplitude halving
    as the frequency doubles (a 1/f spectrum); cheap enough for on-the-fly scenes.
    """
    waves = _WAVES.to(points.dtype)
    total = torch.zeros(points.shape[0], dtype=points.dtype)
    norm = 0.0
    for octave in range(octaves):
        freq = 2 * math.pi * 2**octave / scale
        for w in waves[2 * octave : 2 * octave + 2]:
            phase = points[:, 0] * w[0] + points[:, 1] * w[1] + points[:, 2] * w[2]
            total = total + 0.5**octave * torch.sin(freq * phase + w[3])
            norm += 0.5**octave
    return 0.5 + 0.5 * total / norm


def albedo_at(spec: SceneSpec, points: Tensor, primitive: Tensor) -> Tensor:
    """Albedo ``(N, 3)`` of the primitives ``(N,)`` (global index, >= 0) at ``points (N, 3)``."""
    base, alt = spec.kd_base[primitive], spec.kd_alt[primitive]
    kind, scale = spec.texture[primitive], spec.texture_scale[primitive]
    cells = torch.floor(points / scale[:, None]).sum(-1)
    checker = torch.remainder(cells, 2) < 0.5
    stripes = torch.sin(2 * math.pi * (points * spec.texture_dir[primitive]).sum(-1) / scale) > 0
    t = torch.where(kind == Texture.CHECKER, checker.to(points.dtype),
                    torch.where(kind == Texture.STRIPES, stripes.to(points.dtype), torch.ones_like(scale)))
    noisy = (kind == Texture.NOISE).nonzero(as_tuple=True)[0]
    if noisy.numel():  # the costliest pattern: evaluated only where used
        t[noisy] = fractal_noise(points[noisy], scale[noisy])
    return alt + t[:, None] * (base - alt)


def _objects_only(prims: Primitives) -> Primitives:
    return Primitives(planes=prims.planes[:0], spheres=prims.spheres, boxes=prims.boxes, cylinders=prims.cylinders)


def _trace(spec: SceneSpec, dirs: Tensor, lights: Tensor):
    hit = cast_rays(spec.prims, torch.zeros_like(dirs), dirs)
    valid = torch.isfinite(hit.t)
    t = torch.where(valid, hit.t, torch.zeros_like(hit.t))
    points = dirs * t[:, None]
    facing = (hit.normal * dirs).sum(-1, keepdim=True) > 0
    normals = torch.where(facing, -hit.normal, hit.normal)
    # Renormalised: float32 sphere and cylinder normals drift from unit length by ~1e-5.
    normals = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12) * valid[:, None]
    # The room is convex and every light is inside it, so its planes never block a
    # shadow ray: test the objects only. The origin is nudged off the surface along
    # the camera-facing normal by 2e-4 of its distance (float32 self-hits).
    occluders = _objects_only(spec.prims)
    vis = []
    for light in lights:
        origin = points + 2e-4 * points.norm(dim=-1, keepdim=True) * normals
        blocked = any_hit(occluders, origin, light[None] - origin, 1e-6, torch.ones_like(t))
        vis.append((~blocked).to(points.dtype))
    visibility = torch.stack(vis, -1) if vis else torch.ones(points.shape[0], 0, dtype=points.dtype)
    primitive = hit.primitive.clamp_min(0)
    return valid, t, points, normals, visibility, primitive


def _shade(spec: SceneSpec, trace, falloff: str) -> tuple[Tensor, Tensor]:
    # Unit-exposure radiance (R, 3) without ambient, and the albedo (R, 3), of traced rays.
    valid, _, points, normals, visibility, primitive = trace
    kd = albedo_at(spec, points, primitive) * valid[:, None]
    ks = spec.ks[primitive][:, None] * valid[:, None]
    shininess = torch.where(valid, spec.shininess[primitive], torch.ones_like(points[:, 0]))
    radiance = shade_exact(points, normals, visibility, kd, ks, shininess, spec.light_position,
                           spec.light_relative_intensity, torch.zeros(3, dtype=points.dtype), falloff)
    return radiance * valid[:, None], kd


def _edges(prim: Tensor, visibility: Tensor, kd: Tensor) -> Tensor:
    # (H, W) bool: pixels whose 3x3 neighbourhood changes primitive, shadow or albedo.
    def spread(x: Tensor) -> Tensor:  # (C, H, W) -> max - min over 3x3
        x = x[None]
        return (F.max_pool2d(x, 3, 1, 1) + F.max_pool2d(-x, 3, 1, 1))[0]

    stack = torch.cat([prim.to(kd.dtype)[None], visibility.permute(2, 0, 1), kd.permute(2, 0, 1)], 0)
    change = spread(stack)
    return (change[0] > 0) | (change[1 : 1 + visibility.shape[-1]] > 0).any(0) | (change[-3:] > 0.02).any(0)


def render_spec(spec: SceneSpec, samples: int = 2, falloff: str = "inverse_square") -> RenderedScene:
    """Render ``spec`` exactly; returns the scene file contents with ground truth.

    Args:
        spec: a sampled scene.
        samples: ``samples x samples`` image samples per pixel (1: centre only).
            Adaptive: pixels whose 3x3 neighbourhood shows no change of primitive,
            of any light's visibility or of a checker or stripe
            albedo (> 0.02) keep their centre
            sample, whose value the supersampled average equals there up to the
            smooth shading's curvature; the others get the full grid.
        falloff: ``"inverse_square"`` or ``"none"`` (written into ``meta``).

    The light intensities are the spec's relative ones times one exposure factor,
    chosen so that the 99th percentile of the image equals ``spec.exposure``; the
    ambient term is scaled by the same factor (the model is linear in both).
    """
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    H, W, K = spec.height, spec.width, spec.K
    lights = spec.light_position
    centre_dirs = camera_rays(K, H, W)
    centre = _trace(spec, centre_dirs, lights)
    valid, depth, points, normals, visibility, primitive = centre
    radiance, kd = _shade(spec, centre, falloff)
    ks = spec.ks[primitive][:, None] * valid[:, None]
    shininess = torch.where(valid, spec.shininess[primitive], torch.ones_like(depth))
    supersampled = 0
    if samples > 1:
        # Albedo jumps only where the pattern is discontinuous (checker, stripes).
        kind = spec.texture[primitive]
        jumps = kd * ((kind == Texture.CHECKER) | (kind == Texture.STRIPES))[:, None]
        edge = _edges(primitive.reshape(H, W), visibility.reshape(H, W, -1), jumps.reshape(H, W, 3)).reshape(-1)
        pixels = edge.nonzero(as_tuple=True)[0]
        supersampled = int(pixels.numel())
        if supersampled:
            # Sub-pixel offsets on a regular grid, as camera-ray direction shifts.
            offsets = (torch.arange(samples, dtype=K.dtype) + 0.5) / samples - 0.5
            oy, ox = torch.meshgrid(offsets, offsets, indexing="ij")
            shift = torch.stack([ox.reshape(-1), oy.reshape(-1), torch.zeros(samples * samples, dtype=K.dtype)], -1)
            shift = shift @ torch.linalg.inv(K).T
            dirs = (centre_dirs[pixels, None] + shift[None]).reshape(-1, 3)  # (E * S, 3), pixel-major
            sub_radiance, sub_kd = _shade(spec, _trace(spec, dirs, lights), falloff)
            radiance[pixels] = sub_radiance.unflatten(0, (supersampled, -1)).mean(1)
            kd[pixels] = sub_kd.unflatten(0, (supersampled, -1)).mean(1) * valid[pixels, None]

    unit_image = radiance + kd * spec.ambient_relative
    exposure = spec.exposure / torch.quantile(unit_image[valid].amax(-1), 0.99).clamp_min(1e-6)
    image = unit_image * exposure * valid[:, None]
    intensity = spec.light_relative_intensity * exposure
    ambient = spec.ambient_relative * exposure
    pts = points[valid]
    scene_scale = (pts.amax(0) - pts.amin(0)).norm()
    meta = {"id": f"procedural_{spec.seed}", "generator": GENERATOR_NAME, "falloff": falloff,
            "n_lights": int(lights.shape[0]), "aa_samples": samples, "aa_pixels": supersampled,
            "seed": spec.seed, **spec.meta}
    scene = Scene(
        image=image.reshape(H, W, 3).float(), depth=depth.reshape(H, W).float(), K=K.float(),
        kd=kd.reshape(H, W, 3).float(), meta=meta, ks=ks.reshape(H, W, 1).float(),
        shininess=shininess.reshape(H, W).float(), normals=normals.reshape(H, W, 3).float(),
        ambient=ambient.float(), light_pos=lights.float(), light_intensity=intensity.float(),
        scene_scale=scene_scale.float(),
    )
    return RenderedScene(scene=scene, visibility=visibility.reshape(H, W, -1))
