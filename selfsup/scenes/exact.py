"""Exact ground-truth rendering of a sampled scene by batched ray casting.

Primary rays through pixels, exact shadow rays against the primitives (never the
shadow maps of ``render/``), the Blinn-Phong model of ``../shared/scene-format.md``
with inverse-square falloff by default, and ``samples x samples`` supersampled
anti-aliasing of the image. The stored G-buffer is that of the pixel centre ray
(depth, normals, ks, shininess) and the pixel-averaged albedo, as an RGB-D
sensor with an albedo estimate would give it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from selfsup.scenes.io import Scene
from selfsup.scenes.raycast import (_CHUNK, Bundles, PrimitiveBatch, blocked_bundles, bundle_rays, camera_rays,
                                    cast_bundles, hit_normals, shade_exact)
from selfsup.scenes.sampler import Materials, SceneSpec, Texture

__all__ = ["RenderedScene", "render_spec", "render_specs", "albedo_at", "fractal_noise"]

GENERATOR_NAME = "shadowlight.procedural v1 (exact ray casting)"
_MAX_RAYS = 2**19  # camera rays of one render_specs call: 32 scenes of 128 x 128


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


def albedo_at(materials: Materials, points: Tensor, primitive: Tensor) -> Tensor:
    """Albedo ``(N, 3)`` of the primitives ``(N,)`` (global index, >= 0) at ``points (N, 3)``."""
    base, alt = materials.kd_base.index_select(0, primitive), materials.kd_alt.index_select(0, primitive)
    kind, scale = materials.texture.index_select(0, primitive), materials.texture_scale.index_select(0, primitive)
    cells = torch.floor(points / scale[:, None]).sum(-1)
    checker = torch.remainder(cells, 2) < 0.5
    stripes = torch.sin(2 * math.pi * (points * materials.texture_dir.index_select(0, primitive)).sum(-1) / scale) > 0
    t = torch.where(kind == Texture.CHECKER, checker.to(points.dtype),
                    torch.where(kind == Texture.STRIPES, stripes.to(points.dtype), torch.ones_like(scale)))
    noisy = (kind == Texture.NOISE).nonzero(as_tuple=True)[0]
    if noisy.numel():  # the costliest pattern: evaluated only where used
        t[noisy] = fractal_noise(points[noisy], scale[noisy])
    return alt + t[:, None] * (base - alt)


def _tile_order(height: int, width: int) -> Tensor:
    """Pixel indices ``(H*W,)`` row-major within 8 x 8 tiles, tiles row-major: rays
    listed so come in coherent bundles, which the ray caster culls as a whole."""
    v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    tiles_x = -(-width // 8)
    key = (((v // 8) * tiles_x + u // 8) * 64 + (v % 8) * 8 + u % 8).reshape(-1)
    return key.argsort()


class _Batch:
    """Specs of one image size, cast together: their primitives (:class:`PrimitiveBatch`),
    materials in its global order, and lights padded to ``L``: ``light_position``,
    ``light_intensity (B, L, 3)`` (zero intensity where a scene has fewer)."""

    def __init__(self, specs: list[SceneSpec]):
        self.prims = PrimitiveBatch.of([spec.prims for spec in specs])
        sizes = torch.tensor([spec.materials.kd_base.shape[0] for spec in specs])
        scene_major = (sizes.cumsum(0) - sizes)[self.prims.scene] + self.prims.local
        self.materials = Materials(**{f.name: torch.cat([getattr(spec.materials, f.name) for spec in specs])[scene_major]
                                      for f in dataclasses.fields(Materials)})
        self.n_lights = [spec.light_position.shape[0] for spec in specs]
        L = max(self.n_lights)
        self.light_position = torch.zeros(len(specs), L, 3)
        self.light_intensity = torch.zeros(len(specs), L, 3)
        for b, spec in enumerate(specs):
            self.light_position[b, : self.n_lights[b]] = spec.light_position
            self.light_intensity[b, : self.n_lights[b]] = spec.light_relative_intensity


def _trace(batch: _Batch, dirs: list[Tensor]):
    """Camera rays ``dirs[b] (R_b, 3)`` of each scene (neighbours in a list pointing
    alike, see :func:`_tile_order`), concatenated: ``scene (R,)``, ``valid``, ``t``,
    ``points``, camera-facing ``normals``, cast-shadow ``visibility (R, L)`` and the
    global ``primitive (R,)`` (0 where none)."""
    counts = torch.tensor([x.shape[0] for x in dirs])
    bundles_per = -(-counts // _CHUNK)
    scene_of_bundle = torch.repeat_interleave(torch.arange(len(dirs)), bundles_per)
    first_slot = (bundles_per.cumsum(0) - bundles_per) * _CHUNK
    first_ray = counts.cumsum(0) - counts
    # slot -> ray feeding it (a bundle's padding repeats its scene's last ray); ray -> slot.
    slot_src = torch.cat([first_ray[b] + bundle_rays(torch.arange(int(counts[b]))).reshape(-1)
                          for b in range(len(dirs))])
    scene = torch.repeat_interleave(torch.arange(len(dirs)), counts)
    slot_of_ray = first_slot[scene] + torch.arange(int(counts.sum())) - first_ray[scene]
    flat = torch.cat(dirs)
    N = int(bundles_per.sum())

    def bundled(rays: Tensor) -> Tensor:  # (R, 3) -> (3, N, S)
        return rays.index_select(0, slot_src).unflatten(0, (N, _CHUNK)).permute(2, 0, 1)

    origin = flat.new_zeros(N, 3)
    t, primitive = cast_bundles(batch.prims, Bundles.of(bundled(flat), origin, scene_of_bundle, 0.0))
    t, primitive = t.index_select(0, slot_of_ray), primitive.index_select(0, slot_of_ray)
    valid = primitive >= 0
    t = torch.where(valid, t, torch.zeros_like(t))
    points = flat * t[:, None]
    normal = hit_normals(batch.prims.prims, points, primitive)
    facing = (normal * flat).sum(-1, keepdim=True) > 0
    normals = torch.where(facing, -normal, normal)
    # The room is convex and every light is inside it, so its planes never block a
    # shadow ray: test the objects only. Each ray runs from the light (one origin per
    # bundle) to the point nudged off the surface along the camera-facing normal by
    # 2e-4 of its distance (float32 self-hits), and is blocked by a hit before it.
    target = bundled(points + 2e-4 * points.norm(dim=-1, keepdim=True) * normals)
    end = flat.new_full((N, _CHUNK), 1 - 1e-6)
    visibility = flat.new_ones(flat.shape[0], batch.light_position.shape[1])
    for light in range(batch.light_position.shape[1]):
        lit = torch.tensor([n > light for n in batch.n_lights])[scene_of_bundle].nonzero(as_tuple=True)[0]
        source = batch.light_position[scene_of_bundle[lit], light]  # (N', 3)
        shadow = Bundles.of(target[:, lit] - source.T[:, :, None], source, scene_of_bundle[lit], 0.0, end[lit])
        blocked = torch.zeros(N, _CHUNK, dtype=torch.bool)
        blocked[lit] = blocked_bundles(batch.prims, shadow, objects_only=True).view(-1, _CHUNK)
        visibility[:, light] = (~blocked.reshape(-1).index_select(0, slot_of_ray)).to(flat.dtype)
    return scene, valid, t, points, normals * valid[:, None], visibility, primitive.clamp_min(0)


def _shade(batch: _Batch, trace, falloff: str) -> tuple[Tensor, Tensor]:
    # Unit-exposure radiance (R, 3) without ambient, and the albedo (R, 3), of traced rays.
    scene, valid, _, points, normals, visibility, primitive = trace
    materials = batch.materials
    kd = albedo_at(materials, points, primitive) * valid[:, None]
    ks = materials.ks.index_select(0, primitive)[:, None] * valid[:, None]
    shininess = torch.where(valid, materials.shininess.index_select(0, primitive), torch.ones_like(points[:, 0]))
    radiance = shade_exact(points, normals, visibility, kd, ks, shininess, batch.light_position.index_select(0, scene),
                           batch.light_intensity.index_select(0, scene), torch.zeros(3, dtype=points.dtype), falloff)
    return radiance * valid[:, None], kd


def _edges(prim: Tensor, visibility: Tensor, kd: Tensor) -> Tensor:
    # (B, H, W) bool: pixels whose 3x3 neighbourhood changes primitive, shadow or albedo.
    def largest(x: Tensor) -> Tensor:  # max over 3x3, edges replicated: shifted maxima, 6x faster than max_pool2d
        x = F.pad(x, (1, 1, 1, 1), mode="replicate")
        x = torch.maximum(torch.maximum(x[..., :-2, :], x[..., 1:-1, :]), x[..., 2:, :])
        return torch.maximum(torch.maximum(x[..., :-2], x[..., 1:-1]), x[..., 2:])

    def spread(x: Tensor) -> Tensor:  # (B, C, H, W) -> max - min over 3x3
        return largest(x) + largest(-x)

    stack = torch.cat([prim.to(kd.dtype)[:, None], visibility.permute(0, 3, 1, 2), kd.permute(0, 3, 1, 2)], 1)
    change = spread(stack)
    L = visibility.shape[-1]
    return (change[:, 0] > 0) | (change[:, 1 : 1 + L] > 0).any(1) | (change[:, -3:] > 0.02).any(1)


def render_spec(spec: SceneSpec, samples: int = 2, falloff: str = "inverse_square") -> RenderedScene:
    """Render ``spec`` exactly; returns the scene file contents with ground truth.
    See :func:`render_specs`."""
    return render_specs([spec], samples, falloff)[0]


def render_specs(specs: list[SceneSpec], samples: int = 2, falloff: str = "inverse_square") -> list[RenderedScene]:
    """Render specs of one image size exactly, ray cast together; each result is the
    one :func:`render_spec` gives alone (casting several at once only saves time).

    Args:
        specs: sampled scenes, all of one ``height`` and ``width``.
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
    if not specs:
        return []
    H, W = specs[0].height, specs[0].width
    if any((spec.height, spec.width) != (H, W) for spec in specs):
        raise ValueError(f"render_specs needs specs of one size, got {sorted({(s.height, s.width) for s in specs})}")
    per_call = max(1, _MAX_RAYS // (H * W))
    if len(specs) > per_call:  # bounded memory: a few hundred MB at most
        return [r for i in range(0, len(specs), per_call) for r in render_specs(specs[i : i + per_call], samples, falloff)]
    B = len(specs)
    batch = _Batch(specs)
    order = _tile_order(H, W)
    centre_dirs = [camera_rays(spec.K, H, W) for spec in specs]
    centre = _trace(batch, [dirs[order] for dirs in centre_dirs])
    # Back to pixel order: ray b * H * W + i of the trace is pixel order[i] of scene b.
    to_pixel = (torch.arange(B)[:, None] * (H * W) + order[None]).reshape(-1)
    centre = tuple(torch.empty_like(x).index_copy_(0, to_pixel, x) for x in centre)
    _, valid, depth, points, normals, visibility, primitive = centre
    radiance, kd = _shade(batch, centre, falloff)
    supersampled = [0] * B
    if samples > 1:
        # Albedo jumps only where the pattern is discontinuous (checker, stripes).
        kind = batch.materials.texture[primitive]
        jumps = kd * ((kind == Texture.CHECKER) | (kind == Texture.STRIPES))[:, None]
        # A pixel's primitive as its index within its scene, so that scenes compare alike.
        local = batch.prims.local[primitive]
        edge = _edges(local.reshape(B, H, W), visibility.reshape(B, H, W, -1), jumps.reshape(B, H, W, 3)).reshape(B, -1)
        # Sub-pixel offsets on a regular grid, as camera-ray direction shifts.
        offsets = (torch.arange(samples, dtype=torch.float32) + 0.5) / samples - 0.5
        oy, ox = torch.meshgrid(offsets, offsets, indexing="ij")
        grid = torch.stack([ox.reshape(-1), oy.reshape(-1), torch.zeros(samples * samples)], -1)
        pixels = [order[edge[b][order]] for b in range(B)]  # in tile order
        supersampled = [int(p.numel()) for p in pixels]
        todo = [b for b in range(B) if supersampled[b]]
        if todo:
            sub_dirs = [(centre_dirs[b][pixels[b], None] + (grid.to(specs[b].K.dtype) @ torch.linalg.inv(specs[b].K).T)[None])
                        .reshape(-1, 3) for b in todo]  # (E * S, 3), pixel-major
            sub_batch = _Batch([specs[b] for b in todo])
            sub_radiance, sub_kd = _shade(sub_batch, _trace(sub_batch, sub_dirs), falloff)
            at = torch.cat([b * H * W + pixels[b] for b in todo])
            radiance[at] = sub_radiance.unflatten(0, (-1, samples * samples)).mean(1)
            kd[at] = sub_kd.unflatten(0, (-1, samples * samples)).mean(1) * valid[at, None]
    results = []
    for b, spec in enumerate(specs):
        rows = slice(b * H * W, (b + 1) * H * W)
        results.append(_finish(spec, valid[rows], depth[rows], points[rows], normals[rows],
                               visibility[rows, : batch.n_lights[b]], radiance[rows], kd[rows],
                               batch.materials.ks[primitive[rows]], batch.materials.shininess[primitive[rows]],
                               samples, supersampled[b], falloff))
    return results


def _quantile(values: Tensor, q: float) -> Tensor:
    """``torch.quantile(values, q)`` (linear interpolation) of a 1-D tensor from its top
    values only: a partial sort, 10x faster for the 99th percentile of an image."""
    n = values.numel()
    position = q * (n - 1)
    low = int(position)
    top = torch.topk(values, n - low).values  # descending: top[-1] is sorted[low]
    below, above = top[-1], top[-2] if n - low > 1 else top[-1]
    return below + (position - low) * (above - below)


def _finish(spec: SceneSpec, valid: Tensor, depth: Tensor, points: Tensor, normals: Tensor, visibility: Tensor,
            radiance: Tensor, kd: Tensor, ks: Tensor, shininess: Tensor, samples: int, supersampled: int,
            falloff: str) -> RenderedScene:
    # One scene's exposure, ground truth and file contents from its rays (H * W, ...) in pixel order.
    H, W = spec.height, spec.width
    lights = spec.light_position
    unit_image = radiance + kd * spec.ambient_relative
    exposure = spec.exposure / _quantile(unit_image[valid].amax(-1), 0.99).clamp_min(1e-6)
    image = unit_image * exposure * valid[:, None]
    intensity = spec.light_relative_intensity * exposure
    ambient = spec.ambient_relative * exposure
    pts = points[valid]
    scene_scale = (pts.amax(0) - pts.amin(0)).norm()
    meta = {"id": f"procedural_{spec.seed}", "generator": GENERATOR_NAME, "falloff": falloff,
            "n_lights": int(lights.shape[0]), "aa_samples": samples, "aa_pixels": supersampled,
            "seed": spec.seed, **spec.meta}
    scene = Scene(
        image=image.reshape(H, W, 3).float(), depth=depth.reshape(H, W).float(), K=spec.K.float(),
        kd=kd.reshape(H, W, 3).float(), meta=meta, ks=(ks[:, None] * valid[:, None]).reshape(H, W, 1).float(),
        shininess=torch.where(valid, shininess, torch.ones_like(depth)).reshape(H, W).float(),
        normals=normals.reshape(H, W, 3).float(),
        ambient=ambient.float(), light_pos=lights.float(), light_intensity=intensity.float(),
        scene_scale=scene_scale.float(),
    )
    return RenderedScene(scene=scene, visibility=visibility.reshape(H, W, -1))
