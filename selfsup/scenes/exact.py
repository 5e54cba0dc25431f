"""Exact ground-truth rendering of a sampled scene by batched ray casting.

Primary rays through pixels, exact shadow rays against the primitives (never the
shadow maps of ``render/``), the Blinn-Phong model of ``docs/scene-format.md``
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
from selfsup.scenes.raycast import (_CHUNK, _FAR, _KINDS, Bundles, PrimitiveBatch, _mask, blinn_phong, blocked_bundles,
                                    bundle_rays, cast_bundles, hit_normals)
from selfsup.scenes.sampler import Materials, SceneSpec, Texture

__all__ = ["RenderedScene", "render_spec", "render_specs", "albedo_at", "pattern_at", "material_rows", "fractal_noise",
           "neighbourhood_max"]

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
    """Smooth fractal pattern in [0, 1] at ``points (3, N)`` (by component) with feature
    size ``scale (N,)``.

    A sum of plane waves in fixed directions, two per octave, the amplitude halving
    as the frequency doubles (a 1/f spectrum); cheap enough for on-the-fly scenes.
    """
    if octaves < 1:
        raise ValueError(f"octaves must be >= 1, got {octaves}")
    waves = _WAVES.tolist()
    total = None
    norm = 0.0
    for octave in range(octaves):
        freq = (2 * math.pi * 2**octave) / scale
        for w in waves[2 * octave : 2 * octave + 2]:
            phase = points[0] * w[0] + points[1] * w[1] + points[2] * w[2]
            wave = torch.sin(freq * phase + w[3])
            # The amplitude, a power of two, scales exactly inside the sum: one pass fewer.
            total = wave if total is None else torch.add(total, wave, alpha=0.5**octave)
            norm += 0.5**octave
    return 0.5 + (0.5 / norm) * total


# Rows of a per-primitive material table (:func:`material_rows`).
_KIND, _SCALE, _DIRECTION, _BASE, _ALT, _KS, _SHININESS = 0, 1, slice(2, 5), slice(5, 8), slice(8, 11), 11, 12


def material_rows(materials: Materials) -> Tensor:
    """The material table by rows ``(13, P)``: texture kind, texture scale, stripe
    direction (3), base and alternate albedo (3 each), ks, shininess; one gather
    of its columns gives rays all they need (13 gathers of one value each cost 3x more)."""
    return torch.cat([materials.texture[None].to(materials.kd_base.dtype), materials.texture_scale[None],
                      materials.texture_dir.T, materials.kd_base.T, materials.kd_alt.T, materials.ks[None],
                      materials.shininess[None]]).contiguous()


def pattern_at(material: Tensor, points: Tensor) -> Tensor:
    """Where ``points (3, N)`` fall between the base (1) and the alternate (0) albedo
    of primitives whose :func:`material_rows` columns are ``material (13, N)``: ``(N,)``,
    0 or 1 on checkers and stripes, in [0, 1] on fractal noise, 1 on uniform albedo."""
    kind, scale = material[_KIND], material[_SCALE]
    # Checker and stripes everywhere (a few cheap passes), chosen by float masks.
    inv_scale = 1 / scale
    cells = torch.floor(points[0] * inv_scale) + torch.floor(points[1] * inv_scale) + torch.floor(points[2] * inv_scale)
    # Odd cells take the alternate albedo: half an odd number is no integer (3x faster than a remainder).
    half = cells * 0.5
    odd = _mask(torch.ne, torch.floor(half), half)
    direction = material[_DIRECTION]
    along = points[0] * direction[0] + points[1] * direction[1] + points[2] * direction[2]
    stripes = _mask(torch.gt, torch.sin((2 * math.pi) * along * inv_scale), 0.0)
    is_checker, is_stripes = (_mask(torch.eq, kind, float(pattern)) for pattern in (Texture.CHECKER, Texture.STRIPES))
    t = 1 - is_checker * odd + is_stripes * (stripes - 1)
    noisy = (kind == Texture.NOISE).nonzero(as_tuple=True)[0]
    if noisy.numel():  # the costliest pattern: evaluated only where used
        t.index_copy_(0, noisy, fractal_noise(points.index_select(1, noisy), scale.index_select(0, noisy)))
    return t


def albedo_at(material: Tensor, points: Tensor | None, pattern: Tensor | None = None) -> Tensor:
    """Albedo ``(3, N)`` at ``points (3, N)`` of primitives whose :func:`material_rows`
    columns are ``material (13, N)`` (``pattern``: their :func:`pattern_at`, if known;
    then ``points`` may be None)."""
    t = pattern_at(material, points) if pattern is None else pattern
    base, alt = material[_BASE], material[_ALT]
    return alt + t * (base - alt)


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
        self.material_rows = material_rows(self.materials)
        self.n_lights = [spec.light_position.shape[0] for spec in specs]
        L = max(self.n_lights)
        self.light_position = torch.zeros(len(specs), L, 3)
        self.light_intensity = torch.zeros(len(specs), L, 3)
        for b, spec in enumerate(specs):
            self.light_position[b, : self.n_lights[b]] = spec.light_position
            self.light_intensity[b, : self.n_lights[b]] = spec.light_relative_intensity
        # Each scene's light positions and intensities as one (6 L, B) table: shading gathers
        # its columns per ray (a gather along a last axis is slow).
        self.light_rows = torch.cat([self.light_position, self.light_intensity], 1).reshape(len(specs), -1).T.contiguous()


@dataclass
class _Rays:
    """Traced camera rays, by component: ``scene``, ``valid``, ``t``, global
    ``primitive (R,)`` (0 where none), ``points``, camera-facing ``normals (3, R)``
    (zero where none) and cast-shadow ``visibility (L, R)``."""

    scene: Tensor
    valid: Tensor
    t: Tensor
    primitive: Tensor
    points: Tensor
    normals: Tensor
    visibility: Tensor

    def take(self, index: Tensor) -> "_Rays":
        return _Rays(*(x.index_select(x.dim() - 1, index) for x in self._fields()))

    def narrow(self, start: int, length: int) -> "_Rays":
        return _Rays(*(x.narrow(x.dim() - 1, start, length) for x in self._fields()))

    def _fields(self) -> list[Tensor]:
        return [getattr(self, f.name) for f in dataclasses.fields(self)]


def _surface(batch: _Batch, dirs: Tensor, t: Tensor, primitive: Tensor) -> tuple:
    # (valid, t, points, camera-facing normals) of rays dirs (3, R) that hit primitive (-1: none) at t.
    valid = primitive >= 0
    t = torch.where(valid, t, torch.zeros_like(t))
    points = dirs * t
    normal = hit_normals(batch.prims.prims, points, primitive)
    toward = normal[0] * dirs[0] + normal[1] * dirs[1] + normal[2] * dirs[2]
    return valid, t, points, normal * (1 - 2 * _mask(torch.gt, toward, 0.0))


def _trace(batch: _Batch, dirs: list[Tensor]) -> _Rays:
    """Camera rays ``dirs[b] (3, R_b)`` of each scene (neighbours in a list pointing
    alike, see :func:`_tile_order`), concatenated, with exact shadow rays."""
    counts = torch.tensor([x.shape[1] for x in dirs])
    bundles_per = -(-counts // _CHUNK)
    scene_of_bundle = torch.repeat_interleave(torch.arange(len(dirs)), bundles_per)
    scene = torch.repeat_interleave(torch.arange(len(dirs)), counts)
    flat = torch.cat(dirs, 1)
    N = int(bundles_per.sum())
    if bool((counts % _CHUNK == 0).all()):  # no padding: rays are slots
        slot_src = slot_of_ray = None
    else:
        # slot -> ray feeding it (a bundle's padding repeats its scene's last ray); ray -> slot.
        first_slot = (bundles_per.cumsum(0) - bundles_per) * _CHUNK
        first_ray = counts.cumsum(0) - counts
        slot_src = torch.cat([first_ray[b] + bundle_rays(torch.arange(int(counts[b]))).reshape(-1)
                              for b in range(len(dirs))])
        slot_of_ray = first_slot[scene] + torch.arange(int(counts.sum())) - first_ray[scene]

    def bundled(rays: Tensor) -> Tensor:  # (3, R) -> (3, N, S)
        return (rays if slot_src is None else rays.index_select(1, slot_src)).view(3, N, _CHUNK)

    def unbundled(per_slot: Tensor) -> Tensor:  # (N * S,) -> (R,)
        return per_slot if slot_of_ray is None else per_slot.index_select(0, slot_of_ray)

    t, primitive = cast_bundles(batch.prims, Bundles.of(bundled(flat), flat.new_zeros(N, 3), scene_of_bundle, 0.0))
    primitive = unbundled(primitive)
    valid, t, points, normals = _surface(batch, flat, unbundled(t), primitive)
    # The room is convex and every light is inside it, so its planes never block a
    # shadow ray: test the objects only. Each ray runs from the light (one origin per
    # bundle) to the point nudged off the surface along the camera-facing normal by
    # 2e-4 of its distance (float32 self-hits), and is blocked by a hit before it.
    distance = (points[0] * points[0] + points[1] * points[1] + points[2] * points[2]).sqrt()
    target = bundled(points + (2e-4 * distance) * normals)
    end = flat.new_full((N, _CHUNK), 1 - 1e-6)
    visibility = flat.new_ones(batch.light_position.shape[1], flat.shape[1])
    for light in range(batch.light_position.shape[1]):
        has = torch.tensor([n > light for n in batch.n_lights])[scene_of_bundle]
        if bool(has.all()):
            lit, shadow_target, shadow_end = None, target, end
        else:
            lit = has.nonzero(as_tuple=True)[0]
            shadow_target, shadow_end = target.index_select(1, lit), end.index_select(0, lit)
        owner = scene_of_bundle if lit is None else scene_of_bundle.index_select(0, lit)
        source = batch.light_position[:, light].index_select(0, owner)  # (N', 3)
        shadow = Bundles.of(shadow_target - source.T[:, :, None], source, owner, 0.0, shadow_end)
        hit = blocked_bundles(batch.prims, shadow, objects_only=True)
        if lit is not None:
            hit = torch.zeros(N, _CHUNK, dtype=torch.bool).index_copy_(0, lit, hit.view(-1, _CHUNK)).view(-1)
        visibility[light] = 1 - unbundled(hit).to(flat.dtype)
    return _Rays(scene, valid, t, primitive.clamp_min(0), points, normals, visibility)


# Rays shaded at once: their (3, R) float32 tensors stay within the cache (on the 2-core
# CPU an elementwise pass costs 0.3 ns per element up to 64k rays, 0.9 ns beyond).
_SHADE_RAYS = 65536


def _shade(batch: _Batch, rays: _Rays, falloff: str) -> tuple[Tensor, Tensor, Tensor]:
    """Unit-exposure radiance without ambient and the albedo, each ``(3, R)``, of traced
    rays, and their albedo pattern ``(R,)`` (:func:`pattern_at`)."""
    R = rays.valid.shape[0]
    if R > _SHADE_RAYS:
        radiance, kd, pattern = rays.points.new_empty(3, R), rays.points.new_empty(3, R), rays.points.new_empty(R)
        for start in range(0, R, _SHADE_RAYS):
            length = min(_SHADE_RAYS, R - start)
            for out, part in zip((radiance, kd, pattern), _shade(batch, rays.narrow(start, length), falloff)):
                out.narrow(-1, start, length).copy_(part)
        return radiance, kd, pattern
    valid = rays.valid.to(rays.points.dtype)
    material = batch.material_rows.index_select(1, rays.primitive)  # (13, R)
    pattern = pattern_at(material, rays.points)
    kd = albedo_at(material, rays.points, pattern) * valid
    L = batch.light_position.shape[1]
    lights = batch.light_rows.index_select(1, rays.scene)  # (6 L, R): each ray's light positions and intensities
    diffuse, _ = blinn_phong(rays.points, rays.normals, rays.visibility, None, *lights.view(2, L, 3, -1), falloff,
                             specular=False)
    # Rays that hit nothing are black: their points sit at the camera, where a light padded
    # in (zero intensity, at the origin) of a scene cast beside one with more lights is 0 / 0.
    radiance = torch.where(rays.valid, kd * diffuse, 0.0)
    # The specular term only on rays of specular primitives (most surfaces are matte).
    shiny = (material[_KS] * valid).nonzero(as_tuple=True)[0]
    if shiny.numel():
        _, specular = blinn_phong(rays.points.index_select(1, shiny), rays.normals.index_select(1, shiny),
                                  rays.visibility.index_select(1, shiny), material[_SHININESS].index_select(0, shiny),
                                  *lights.index_select(1, shiny).view(2, L, 3, -1), falloff, diffuse=False)
        radiance.index_add_(1, shiny, material[_KS].index_select(0, shiny) * specular)
    return radiance, kd, pattern


def neighbourhood_max(x: Tensor) -> Tensor:
    """Maximum over each pixel's 3x3 neighbourhood of ``x (..., H, W)`` (the image's
    edge pixels over the part inside): shifted maxima, 6x faster than ``max_pool2d`` on CPU."""
    return _neighbourhood(x, torch.maximum)


def _neighbourhood(x: Tensor, combine) -> Tensor:
    # combine (an associative elementwise op) over each pixel's 3x3 neighbourhood, edges replicated.
    x = F.pad(x[None] if x.dim() == 2 else x, (1, 1, 1, 1), mode="replicate").view(*x.shape[:-2], x.shape[-2] + 2, -1)
    x = combine(combine(x[..., :-2, :], x[..., 1:-1, :]), x[..., 2:, :])
    return combine(combine(x[..., :-2], x[..., 1:-1]), x[..., 2:])


# Albedo classes of a pixel's centre sample for the anti-aliasing (:func:`_edges`): 0 no
# checker or stripes there (or no surface: albedo 0), 1 its alternate, 2 its base albedo.
# Pairs of classes are bits: 0-1, 0-2, 1-2.
_CLASS_PAIRS = ((0, 1), (0, 2), (1, 2))


def _albedo_jumps(material_rows: Tensor) -> Tensor:
    """Per primitive ``(P,)`` uint8: the bits of the class pairs whose albedos differ by more
    than 0.02 in a channel, computed as :func:`albedo_at` computes them."""
    side = material_rows[_KIND]
    values = torch.stack([torch.zeros_like(material_rows[_ALT]), albedo_at(material_rows, None, torch.zeros_like(side)),
                          albedo_at(material_rows, None, torch.ones_like(side))])  # (3 classes, 3, P)
    bits = torch.zeros(side.shape[0], dtype=torch.uint8)
    for bit, (i, j) in enumerate(_CLASS_PAIRS):
        bits |= ((values[i] - values[j]).abs() > 0.02).any(0).to(torch.uint8) << bit
    return bits


def _edges(local: Tensor, visibility: Tensor, albedo_class: Tensor, jumps: Tensor) -> tuple[Tensor, Tensor]:
    """Pixels ``(B, H, W)`` whose 3x3 neighbourhood changes primitive (``local (B, H, W)``,
    its index within its scene) or shadow of any light (``visibility (L, B, H, W)``, 0 or 1),
    and those whose only change is an albedo jump by more than 0.02 in a channel
    (``albedo_class (B, H, W)`` uint8, see :data:`_CLASS_PAIRS`; ``jumps (B, H, W)``: the
    :func:`_albedo_jumps` bits of each pixel's primitive). (Four neighbours would do for
    straight edges, but not for checker corners or stripes under two pixels wide.)

    The neighbourhood is compared through one integer key of primitive and shadows and one
    set of albedo classes per pixel: the same pixels as the range of those values (5x less
    memory traffic than float ranges of each)."""
    L = visibility.shape[0]
    dtype = torch.int16 if (int(local.max()) + 1) << L < 2**15 else torch.int64
    key = local.to(dtype)
    for light in range(L):
        key = key * 2 + visibility[light].to(dtype)
    geometry = neighbourhood_max(key) != -neighbourhood_max(-key)
    seen = _neighbourhood(torch.ones_like(albedo_class) << albedo_class, torch.bitwise_or)  # bit k: class k near
    pairs = torch.zeros_like(seen)
    for bit, (i, j) in enumerate(_CLASS_PAIRS):
        both = (1 << i) | (1 << j)
        pairs |= ((seen & both) == both).to(torch.uint8) << bit
    return geometry, ((pairs & jumps) != 0) & ~geometry


def _same_primitive(batch: _Batch, centre: _Rays, dirs: Tensor) -> tuple[_Rays, Tensor]:
    """Sub-pixel rays ``dirs (3, E, S)`` of ``E`` pixels whose 3x3 neighbourhood shows
    one primitive and one shadow (``centre``: their centre samples), cast against
    that primitive alone and with its visibility: ``E * S`` traced rays, pixel-major,
    and ``missed (E,)``: pixels where one of them misses the primitive after all."""
    E, S = dirs.shape[1], dirs.shape[2]
    t = dirs.new_full((E, S), _FAR)
    first = batch.prims.first
    bounds = first[1:] + [batch.prims.local.shape[0]]
    for k, (kind, fn) in enumerate(_KINDS):
        rows = ((centre.primitive >= first[k]) & (centre.primitive < bounds[k])).nonzero(as_tuple=True)[0]
        if rows.numel():
            table = getattr(batch.prims.prims, kind).index_select(0, centre.primitive.index_select(0, rows) - first[k])
            t.index_copy_(0, rows, fn(table, dirs.new_zeros(3, 1, 1), dirs.index_select(1, rows), 0.0))
    missed = (t >= _FAR).any(1)
    primitive = torch.where(missed, -1, centre.primitive).repeat_interleave(S)
    scene = centre.scene.repeat_interleave(S)
    valid, t, points, normals = _surface(batch, dirs.reshape(3, E * S), t.reshape(-1), primitive)
    return _Rays(scene, valid, t, primitive.clamp_min(0), points, normals, centre.visibility.repeat_interleave(S, 1)), missed


def render_spec(spec: SceneSpec, samples: int = 2, falloff: str = "inverse_square") -> RenderedScene:
    """Render ``spec`` exactly; returns the scene file contents with ground truth.
    See :func:`render_specs`."""
    return render_specs([spec], samples, falloff)[0]


def _supersample(specs: list[SceneSpec], batch: "_Batch", centre: "_Rays", centre_dirs: Tensor, inverse_K: Tensor,
                 order: Tensor, radiance: Tensor, kd: Tensor, pattern: Tensor, samples: int, falloff: str) -> list[int]:
    """Adaptive ``samples x samples`` supersampling of :func:`render_specs` (its docstring says
    where): ``radiance`` and ``kd`` ``(3, B * H * W)`` averaged in place over each chosen
    pixel's samples; returns each scene's count of supersampled pixels."""
    B, H, W = len(specs), specs[0].height, specs[0].width
    # Albedo jumps only where the pattern is discontinuous (checker, stripes): there the
    # pattern is 0 or 1, the class 1 or 2; elsewhere, and off the surfaces, class 0.
    kind = batch.materials.texture.index_select(0, centre.primitive)
    patterned = centre.valid & ((kind == Texture.CHECKER) | (kind == Texture.STRIPES))
    albedo_class = (patterned * (1 + pattern)).to(torch.uint8)
    # A pixel's primitive as its index within its scene, so that scenes compare alike.
    local = batch.prims.local.index_select(0, centre.primitive)
    # Pixels without a surface count as their scene's first primitive (as in local), so
    # they take its jumps: global index of (scene, local).
    width = int(batch.prims.local.max()) + 1
    global_of = torch.zeros(B * width, dtype=torch.long)
    global_of[batch.prims.scene * width + batch.prims.local] = torch.arange(batch.prims.local.shape[0])
    jumps = _albedo_jumps(batch.material_rows).index_select(0, global_of.index_select(0, centre.scene * width + local))
    geometry, albedo = _edges(local.view(B, H, W), centre.visibility.view(-1, B, H, W), albedo_class.view(B, H, W),
                              jumps.view(B, H, W))
    # Sub-pixel offsets on a regular grid, as camera-ray direction shifts (3, S) per scene.
    offsets = (torch.arange(samples, dtype=torch.float32) + 0.5) / samples - 0.5
    oy, ox = torch.meshgrid(offsets, offsets, indexing="ij")
    grid = torch.stack([ox.reshape(-1), oy.reshape(-1), torch.zeros(samples * samples)])
    shift = inverse_K @ grid  # (B, 3, S)
    all_dirs = centre_dirs.transpose(0, 1).reshape(3, B * H * W)

    def sub_dirs(at: Tensor) -> Tensor:  # (3, E, S) of pixels at (E,) (global)
        return all_dirs.index_select(1, at)[:, :, None] + shift.index_select(0, at // (H * W)).permute(1, 0, 2)

    def average(at: Tensor, sub: _Rays, sub_batch: _Batch) -> None:  # the S samples of pixels at (E,)
        sub_radiance, sub_kd, _ = _shade(sub_batch, sub, falloff)
        radiance.index_copy_(1, at, sub_radiance.unflatten(1, (-1, samples * samples)).mean(2))
        kd.index_copy_(1, at, sub_kd.unflatten(1, (-1, samples * samples)).mean(2) * centre.valid.index_select(0, at))

    at = albedo.view(-1).nonzero(as_tuple=True)[0]
    if at.numel():
        sub, missed = _same_primitive(batch, centre.take(at), sub_dirs(at))
        average(at, sub, batch)
        del sub  # freed for the arrays that follow
        geometry.view(-1)[at[missed]] = True  # traced in full below, which overwrites them
    full = geometry.view(B, -1)
    pixels = [order[full[b].index_select(0, order)] for b in range(B)]  # in tile order
    supersampled = [int(x) for x in (full | albedo.view(B, -1)).sum(1)]
    todo = [b for b in range(B) if pixels[b].numel()]
    if todo:
        at = torch.cat([b * H * W + pixels[b] for b in todo])
        sizes = [pixels[b].numel() * samples * samples for b in todo]
        sub_batch = _Batch([specs[b] for b in todo])
        average(at, _trace(sub_batch, list(sub_dirs(at).reshape(3, -1).split(sizes, 1))), sub_batch)
    return supersampled


def render_specs(specs: list[SceneSpec], samples: int = 2, falloff: str = "inverse_square") -> list[RenderedScene]:
    """Render specs of one image size exactly, ray cast together; each result is the
    one :func:`render_spec` gives alone (casting several at once only saves time).

    Args:
        specs: sampled scenes, all of one ``height`` and ``width``.
        samples: ``samples x samples`` image samples per pixel (1: centre only).
            Adaptive: pixels whose 3x3 neighbourhood shows no change of primitive,
            of any light's visibility or of a checker or stripe albedo (> 0.02)
            keep their centre sample, whose value the supersampled average equals
            there up to the smooth shading's curvature. Where primitive or
            visibility change, the full grid is traced with its own shadow rays;
            where only the albedo jumps, the grid's rays are cast against the
            centre's primitive alone and keep its visibility (a pixel where one of
            them misses that primitive is traced in full). The fractal albedo is
            not judged, so it stays point-sampled: against a brute-force 2x2
            average (four renders with shifted principal points; measured ad hoc
            2026-11-23 on five 128x128 scenes), scenes with much of it differ by
            more than 1% on up to an eighth of their pixels, without it on
            0.01-0.5%. Judging it by the same 0.02 rule brings them to 0.01-0.5%
            too, but supersamples 59% of pixels instead of 37%: 30% more time.
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
    # Camera rays through pixel centres with z = 1, (B, 3, H * W): in pixel order, and in tile order to trace.
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    pixels = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(H * W)])
    inverse_K = torch.linalg.inv(torch.stack([spec.K.float() for spec in specs]))
    centre_dirs = inverse_K @ pixels
    # Back to pixel order: pixel i of scene b is ray b * H * W + rank[i] of the trace, rank =
    # order.argsort() (the traced arrays in tile order are freed at once).
    pixel_rays = (torch.arange(B)[:, None] * (H * W) + order.argsort()[None]).reshape(-1)
    centre = _trace(batch, list(inverse_K @ pixels[:, order])).take(pixel_rays)
    radiance, kd, pattern = _shade(batch, centre, falloff)
    supersampled = [0] * B
    if samples > 1:
        supersampled = _supersample(specs, batch, centre, centre_dirs, inverse_K, order, radiance, kd, pattern, samples,
                                    falloff)
    # Each scene's image at unit exposure, ambient included, (3, B, H * W), and the 99th
    # percentile of its brightest channel on valid pixels, which fixes its exposure.
    ambient = torch.stack([spec.ambient_relative for spec in specs]).T[:, :, None]
    unit_image = radiance.view(3, B, H * W) + kd.view(3, B, H * W) * ambient
    brightest = torch.maximum(torch.maximum(unit_image[0], unit_image[1]), unit_image[2])
    valid, points = centre.valid.view(B, H * W), centre.points.view(3, B, H * W)
    quantile = _quantiles(brightest, valid, 0.99)
    # Each scene's extent: the diagonal of its valid points' box (masked extremes: 2x faster than selecting them).
    box = torch.where(valid, points, -math.inf).amax(2) - torch.where(valid, points, math.inf).amin(2)  # (3, B)
    scene_scale = box.T.contiguous().norm(dim=1)
    results = []
    for b, spec in enumerate(specs):
        rows = slice(b * H * W, (b + 1) * H * W)
        primitive = centre.primitive[rows]
        results.append(_finish(spec, centre.valid[rows], centre.t[rows], centre.normals[:, rows],
                               centre.visibility[: batch.n_lights[b], rows], unit_image[:, b], quantile[b], scene_scale[b],
                               kd[:, rows],
                               batch.materials.ks.index_select(0, primitive),
                               batch.materials.shininess.index_select(0, primitive), samples, supersampled[b], falloff))
    return results


def _quantiles(values: Tensor, valid: Tensor, q: float) -> Tensor:
    """``torch.quantile(values[b][valid[b]], q)`` (linear interpolation) of each row of
    ``values, valid (B, N)``: ``(B,)``, 0 for a row without valid values. From the rows'
    top values only, one partial sort for all rows: 10x faster than a full sort for the
    99th percentile of an image, and 2x faster than a partial sort per row."""
    counts = valid.sum(1).tolist()
    lows = [int(q * (n - 1)) if n else 0 for n in counts]
    k = max(n - low for n, low in zip(counts, lows))
    if k == 0:
        return values.new_zeros(values.shape[0])
    top = torch.topk(torch.where(valid, values, -math.inf), k, dim=1).values  # descending: top[b, n - low - 1] is sorted[low]
    out = []
    for b, (n, low) in enumerate(zip(counts, lows)):
        if not n:
            out.append(values.new_zeros(()))
            continue
        below, above = top[b, n - low - 1], top[b, n - low - 2] if n - low > 1 else top[b, n - low - 1]
        out.append(below + (q * (n - 1) - low) * (above - below))
    return torch.stack(out)


def _finish(spec: SceneSpec, valid: Tensor, depth: Tensor, normals: Tensor, visibility: Tensor,
            unit_image: Tensor, brightest_quantile: Tensor, scene_scale: Tensor, kd: Tensor, ks: Tensor,
            shininess: Tensor, samples: int, supersampled: int, falloff: str) -> RenderedScene:
    # One scene's exposure, ground truth and file contents from its rays in pixel order: valid, depth, ks,
    # shininess (H * W,); normals, unit_image (ambient included), kd (3, H * W); visibility (L, H * W);
    # brightest_quantile: the 99th percentile of the unit image's brightest channel on valid pixels;
    # scene_scale: the extent of the valid points.
    H, W = spec.height, spec.width
    lights = spec.light_position
    exposure = spec.exposure / brightest_quantile.clamp_min(1e-6)
    image = unit_image * (exposure * valid)
    intensity = spec.light_relative_intensity * exposure
    ambient = spec.ambient_relative * exposure
    meta = {"id": f"procedural_{spec.seed}", "generator": GENERATOR_NAME, "falloff": falloff,
            "n_lights": int(lights.shape[0]), "aa_samples": samples, "aa_pixels": supersampled,
            "seed": spec.seed, **spec.meta}

    def image_of(x: Tensor) -> Tensor:  # (C, H * W) -> (H, W, C) float32
        return x.T.reshape(H, W, -1).float()

    scene = Scene(
        image=image_of(image), depth=depth.reshape(H, W).float(), K=spec.K.float(),
        kd=image_of(kd), meta=meta, ks=(ks * valid).reshape(H, W, 1).float(),
        shininess=torch.where(valid, shininess, torch.ones_like(depth)).reshape(H, W).float(),
        normals=image_of(normals),
        ambient=ambient.float(), light_pos=lights.float(), light_intensity=intensity.float(),
        scene_scale=scene_scale.float(),
    )
    return RenderedScene(scene=scene, visibility=image_of(visibility))
