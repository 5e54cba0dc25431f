"""Virtual object insertion by differential rendering (Debevec 1998).

An object (a sphere, a cube, or a triangle mesh from a Wavefront OBJ file) is
added to the scene's geometry by ray casting it into the G-buffer; the scene is
rendered with and without it under the estimated lights, and the difference
(the object's shading where it is, its cast shadow and the light it blocks
elsewhere) is added to the real image. Where the estimated lights are wrong,
the inserted shadow disagrees with the real ones: this is the picture users
judge an estimate by.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from render import GBuffer, Material, PointLights, render_image
from selfsup.scenes.io import Scene, render_inputs

__all__ = ["Surface", "Sphere", "Mesh", "load_obj", "default_sphere", "place_object", "insert_object", "insert_sphere",
           "lights_from_record", "insert_files"]


@dataclass(kw_only=True)
class Surface:
    """The inserted object's Blinn-Phong material: diffuse ``albedo (3,)``, specular ``ks``, ``shininess``."""

    albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
    ks: float = 0.2
    shininess: float = 40.0


@dataclass
class Sphere(Surface):
    """``centre (3,)`` camera-frame metres, ``radius`` metres, and its :class:`Surface`."""

    centre: Tensor
    radius: float

    def __post_init__(self):
        if not self.radius > 0 or not bool(torch.isfinite(self.centre).all()):
            raise ValueError(f"sphere needs a finite centre and a radius > 0, got {self.centre.tolist()}, {self.radius}")

    def hits(self, K: Tensor, H: int, W: int) -> tuple[Tensor, Tensor]:
        """Depth (z) of the first hit per pixel ``(H, W)`` (inf for none) and unit normals ``(H, W, 3)``."""
        rays = _pixel_rays(K, H, W)
        c = self.centre.to(K.dtype)
        a = (rays * rays).sum(-1)
        b = (rays * c).sum(-1)
        disc = b * b - a * ((c * c).sum() - self.radius**2)
        t = (b - disc.clamp_min(0).sqrt()) / a
        hit = (disc > 0) & (t > 0)
        depth = torch.where(hit, t, torch.full_like(t, float("inf")))
        normals = (rays * t[..., None] - c) / self.radius
        return depth, normals


@dataclass
class Mesh(Surface):
    """A triangle mesh in the camera frame: ``vertices (V, 3)`` metres, ``faces (F, 3)``
    vertex indices, and its :class:`Surface`. Shading uses flat face normals turned
    towards the camera."""

    vertices: Tensor
    faces: Tensor

    def __post_init__(self):
        if self.vertices.dim() != 2 or self.vertices.shape[-1] != 3 or self.vertices.shape[0] < 3:
            raise ValueError(f"mesh vertices must have shape (V >= 3, 3), got {tuple(self.vertices.shape)}")
        if self.faces.dim() != 2 or self.faces.shape[-1] != 3 or self.faces.shape[0] < 1:
            raise ValueError(f"mesh faces must have shape (F >= 1, 3), got {tuple(self.faces.shape)}")
        if not bool(torch.isfinite(self.vertices).all()):
            raise ValueError("mesh vertices hold non-finite values")
        if int(self.faces.min()) < 0 or int(self.faces.max()) >= self.vertices.shape[0]:
            raise ValueError(f"mesh faces index vertices outside 0..{self.vertices.shape[0] - 1}")

    @staticmethod
    def cube() -> "Mesh":
        """The cube ``[-1, 1]^3`` (12 triangles), to be placed with :func:`place_object`."""
        corners = torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        faces = torch.tensor([tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))])
        return Mesh(corners, faces)

    def hits(self, K: Tensor, H: int, W: int, chunk: int = 1 << 22) -> tuple[Tensor, Tensor]:
        """Depth (z) of the first hit per pixel ``(H, W)`` (inf for none) and unit normals ``(H, W, 3)``.

        Moller-Trumbore against every triangle, in chunks of about ``chunk`` ray-triangle pairs.
        """
        rays = _pixel_rays(K, H, W).reshape(-1, 3)  # z = 1: the hit's t is its depth
        tri = self.vertices.to(K.dtype)[self.faces]  # (F, 3, 3)
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        normal = torch.nn.functional.normalize(torch.cross(e1, e2, dim=-1), dim=-1)
        depth = torch.full((rays.shape[0],), float("inf"), dtype=K.dtype)
        face = torch.zeros(rays.shape[0], dtype=torch.long)
        step = max(1, chunk // max(1, rays.shape[0]))
        for start in range(0, tri.shape[0], step):
            sl = slice(start, start + step)
            p = torch.cross(rays[:, None], e2[None, sl], dim=-1)  # (N, f, 3)
            det = (e1[None, sl] * p).sum(-1)
            ok = det.abs() > 1e-12
            inv = 1 / torch.where(ok, det, torch.ones_like(det))
            s = -tri[None, sl, 0]  # ray origin (0) minus vertex 0
            u = (s * p).sum(-1) * inv
            q = torch.cross(s, e1[None, sl].expand_as(s), dim=-1)
            v = (rays[:, None] * q).sum(-1) * inv
            t = (e2[None, sl] * q).sum(-1) * inv
            hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
            t = torch.where(hit, t, torch.full_like(t, float("inf")))
            best, index = t.min(-1)
            closer = best < depth
            depth = torch.where(closer, best, depth)
            face = torch.where(closer, index + start, face)
        n = normal[face]
        n = torch.where(((n * rays).sum(-1) > 0)[:, None], -n, n)  # face the camera
        return depth.reshape(H, W), n.reshape(H, W, 3)


def load_obj(path: str | Path) -> Mesh:
    """The triangles of a Wavefront OBJ file (``v`` and ``f`` lines; polygons are fanned
    into triangles; texture and normal indices are ignored)."""
    vertices, faces = [], []
    for number, line in enumerate(Path(path).read_text().splitlines(), 1):
        parts = line.split()
        try:
            if parts[:1] == ["v"]:
                vertices.append([float(x) for x in parts[1:4]])
            elif parts[:1] == ["f"]:
                index = [int(p.split("/")[0]) for p in parts[1:]]
                index = [i - 1 if i > 0 else len(vertices) + i for i in index]  # 1-based; negative: relative
                faces.extend([index[0], index[k], index[k + 1]] for k in range(1, len(index) - 1))
        except (ValueError, IndexError):
            raise ValueError(f"{path}:{number}: cannot read {line.strip()!r}") from None
    if not vertices or not faces:
        raise ValueError(f"{path} has no triangles (needs 'v' and 'f' lines)")
    return Mesh(torch.tensor(vertices, dtype=torch.float32), torch.tensor(faces, dtype=torch.long))


def _pixel_rays(K: Tensor, H: int, W: int) -> Tensor:
    # Camera rays (H, W, 3) through the pixel centres, scaled to z = 1.
    v, u = torch.meshgrid(torch.arange(H, dtype=K.dtype), torch.arange(W, dtype=K.dtype), indexing="ij")
    return torch.stack([u, v, torch.ones_like(u)], -1) @ torch.linalg.inv(K).T


def _resting_point(gbuffer: GBuffer, pixel: tuple[float, float]) -> tuple[Tensor, Tensor, float]:
    # The visible point nearest `pixel` (fractions of width, height) on an upward-facing
    # surface (normal within 45 degrees of the camera's up, -y), or on any surface when
    # none faces up; its normal; the valid points' bounding-box diagonal.
    mask = gbuffer.mask[0]
    if not bool(mask.any()):
        raise ValueError("the scene has no valid pixel to put an object on")
    H, W = mask.shape
    upward = mask & (-gbuffer.normals[0, ..., 1] > 0.7)
    v, u = torch.nonzero(upward if bool(upward.any()) else mask, as_tuple=True)
    target = torch.tensor([pixel[1] * (H - 1), pixel[0] * (W - 1)])
    nearest = ((v - target[0]) ** 2 + (u - target[1]) ** 2).argmin()
    valid = gbuffer.points[0][mask]
    return (gbuffer.points[0, v[nearest], u[nearest]], gbuffer.normals[0, v[nearest], u[nearest]],
            float((valid.amax(0) - valid.amin(0)).norm()))


def default_sphere(gbuffer: GBuffer, pixel: tuple[float, float] = (0.5, 0.7), size: float = 0.05) -> Sphere:
    """A sphere resting on the upward-facing surface (normal within 45 degrees of the
    camera's up, -y) nearest to ``pixel`` (fractions of width, height), or on any
    surface when none faces up; its radius ``size`` times the valid points'
    bounding-box diagonal."""
    point, normal, diagonal = _resting_point(gbuffer, pixel)
    radius = size * diagonal
    return Sphere(centre=point + radius * normal, radius=radius)


def _check_placement(pixel: tuple[float, float], size: float) -> None:
    if not (len(pixel) == 2 and all(0 <= float(f) <= 1 for f in pixel)):
        raise ValueError(f"insert.pixel must be two fractions of the width and height in [0, 1], got {list(pixel)}")
    if not (math.isfinite(size) and size > 0):
        raise ValueError(f"insert.size must be > 0 (of the scene's bounding-box diagonal), got {size}")


def place_object(gbuffer: GBuffer, obj: Sphere | Mesh, pixel: tuple[float, float] = (0.5, 0.7),
                 size: float = 0.05) -> Sphere | Mesh:
    """``obj`` resting where :func:`default_sphere` puts its sphere, ``size`` times the
    scene's bounding-box diagonal in radius (a mesh: half its largest side). A mesh's
    own +y axis (the OBJ convention's up) is turned along the surface normal."""
    _check_placement(pixel, size)
    if isinstance(obj, Sphere):
        placed = default_sphere(gbuffer, pixel, size)
        return dataclasses.replace(obj, centre=placed.centre, radius=placed.radius)
    point, normal, diagonal = _resting_point(gbuffer, pixel)
    lo, hi = obj.vertices.amin(0), obj.vertices.amax(0)
    scale = size * diagonal / float((hi - lo).max().clamp_min(1e-12) / 2)
    local = (obj.vertices - (lo + hi) / 2).to(point.dtype) * scale
    across = torch.tensor([1.0, 0.0, 0.0], dtype=point.dtype)
    if float((across * normal).sum().abs()) > 0.9:  # a normal along x: build the frame from z instead
        across = torch.tensor([0.0, 0.0, 1.0], dtype=point.dtype)
    x_axis = torch.nn.functional.normalize(across - (across * normal).sum() * normal, dim=0)
    rotation = torch.stack([x_axis, normal, torch.cross(x_axis, normal, dim=0)], 1)  # local -> camera
    vertices = point + local @ rotation.T - normal * local[:, 1].min()
    return dataclasses.replace(obj, vertices=vertices)


def lights_from_record(record: dict) -> tuple[Tensor, Tensor, Tensor]:
    """``(positions (L, 3), intensities (L, 3), ambient (3,))`` of an estimate's JSON record."""
    name = f"estimate record {record.get('id', '?')}"
    try:
        position = torch.tensor([light["position"] for light in record["lights"]], dtype=torch.float32)
        intensity = torch.tensor([light["intensity"] for light in record["lights"]], dtype=torch.float32)
        ambient = torch.tensor(record.get("ambient", [0.0, 0.0, 0.0]), dtype=torch.float32)
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{name} lacks lights/position/intensity or holds a ragged list: {error}") from None
    L = len(record["lights"])
    # Three finite numbers each: three lights of two coordinates were reshaped silently into two of three.
    for field, value, shape in (("positions", position, (L, 3)), ("intensities", intensity, (L, 3)),
                                ("ambient", ambient, (3,))):
        if ((L or field == "ambient") and tuple(value.shape) != shape) or not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name}: its {field} must be three finite numbers{'' if field == 'ambient' else ' each'}, "
                             f"got {value.tolist()}")
    return position.reshape(-1, 3), intensity.reshape(-1, 3), ambient


def insert_object(scene: Scene, position: Tensor, intensity: Tensor, ambient: Tensor, obj: Sphere | Mesh,
                  shadows: str = "epipolar") -> tuple[Tensor, Tensor]:
    """The scene's image ``(H, W, 3)`` with ``obj`` (placed in the camera frame) inserted
    under the given lights (``(L, 3)`` positions and intensities, ambient ``(3,)``), and
    the object's mask ``(H, W)``."""
    gbuffer, material, _ = render_inputs(scene)
    H, W = scene.depth.shape
    depth, normals = obj.hits(scene.K, H, W)
    scene_depth = torch.where(gbuffer.mask[0], scene.depth, torch.full_like(scene.depth, float("inf")))
    on_object = depth < scene_depth
    with_depth = torch.where(on_object, depth, scene.depth)
    with_normals = torch.where(on_object[..., None], normals, gbuffer.normals[0])
    g_with = GBuffer.from_depth(torch.where(torch.isfinite(with_depth), with_depth, torch.zeros_like(with_depth))[None],
                                scene.K[None], with_normals[None])
    albedo = torch.tensor(obj.albedo, dtype=scene.kd.dtype)
    kd = torch.where(on_object[..., None], albedo, scene.kd)[None]
    ks_scene = material.ks if material.ks is not None else torch.zeros(1, H, W, 1)
    ks = torch.where(on_object[None, ..., None], torch.full_like(ks_scene, obj.ks), ks_scene)
    shininess = torch.as_tensor(material.shininess, dtype=kd.dtype).expand(1, H, W)
    shininess = torch.where(on_object[None], torch.tensor(obj.shininess, dtype=kd.dtype), shininess)
    m_with = Material(kd=kd, ks=ks, shininess=shininess)
    m_without = Material(kd=material.kd, ks=ks_scene, shininess=shininess)
    lights = PointLights(position=position[None].to(kd.dtype), intensity=intensity[None].to(kd.dtype))
    options = dict(falloff=scene.falloff, shadows=shadows)
    with torch.no_grad():
        rendered_with = render_image(g_with, m_with, lights, ambient[None].to(kd.dtype), **options)[0].permute(1, 2, 0)
        rendered_without = render_image(gbuffer, m_without, lights, ambient[None].to(kd.dtype), **options)[0].permute(1, 2, 0)
    real = torch.where(torch.isfinite(scene.image), scene.image, torch.zeros_like(scene.image))
    return torch.where(on_object[..., None], rendered_with, relit(real, rendered_with, rendered_without)), on_object


def relit(real: Tensor, rendered_with: Tensor, rendered_without: Tensor, lit: float = 0.05) -> Tensor:
    """The real image ``(..., 3)`` with the object's effect on the scene: each pixel scaled
    by ``rendered_with / rendered_without`` where the scene's own rendering is at least
    ``lit`` of its median (the ratio keeps the real surface's colour under an albedo the
    estimate only assumed: a shadow on a green floor stays green), the difference added
    elsewhere (where the rendering is dark the ratio says nothing)."""
    level = rendered_without.flatten().median().clamp_min(1e-30) * lit
    ratio = rendered_with / rendered_without.clamp_min(1e-30)
    by_ratio = real * ratio
    return torch.where(rendered_without > level, by_ratio, real + rendered_with - rendered_without).clamp_min(0)


def insert_sphere(scene: Scene, position: Tensor, intensity: Tensor, ambient: Tensor, sphere: Sphere,
                  shadows: str = "epipolar") -> tuple[Tensor, Tensor]:
    """:func:`insert_object` for a sphere (kept for callers of the first API)."""
    return insert_object(scene, position, intensity, ambient, sphere, shadows)


def insert_files(scene: str, output: str, estimates: str | None = None, size: float = 0.05,
                 pixel: tuple[float, float] = (0.5, 0.7), shadows: str = "epipolar", object: str = "sphere") -> Path:
    """Write ``output`` (PNG): the real image, the object inserted under the estimated
    lights (from ``estimates``, a JSON Lines file of ``mode=estimate``, or estimated
    now with the default method when None) and, when the file has them, under the true lights.

    ``object``: ``sphere``, ``cube``, or the path of a Wavefront OBJ file."""
    from skimage.io import imsave

    from selfsup.estimation.options import EstimateOptions
    from selfsup.estimation.stages import estimate_scene
    from selfsup.model import scene_frame
    from selfsup.scenes.generate import to_rgb8
    from selfsup.scenes.capture import read_input

    _check_placement(pixel, size)  # before any estimate is made
    if object == "sphere":
        shape = Sphere(centre=torch.zeros(3), radius=1.0)
    elif object == "cube":
        shape = Mesh.cube()
    elif str(object).lower().endswith(".obj"):
        shape = load_obj(object)
    else:
        raise ValueError(f"insert.object must be sphere, cube or an .obj file, got {object!r}")
    scene = read_input(scene)  # a scene file, or a colour image of a capture folder
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
    placed = place_object(gbuffer, shape, tuple(pixel), size)
    panels = [scene.image]
    estimated, _ = insert_object(scene, *lights_from_record(record), placed, shadows)
    panels.append(estimated)
    if scene.light_pos is not None:
        ambient = scene.ambient if scene.ambient is not None else torch.zeros(3)
        truth, _ = insert_object(scene, scene.light_pos, scene.light_intensity, ambient, placed, shadows)
        panels.append(truth)
    exposure = scene_frame(scene.image.permute(2, 0, 1)[None], gbuffer).exposure[0]
    gap = np.full((scene.image.shape[0], 4, 3), 255, np.uint8)
    row = [part for panel in panels for part in (to_rgb8((panel / exposure).clamp(0, 1) ** (1 / 2.2)), gap)][:-1]
    path = Path(output)
    path.parent.mkdir(parents=True, exist_ok=True)
    imsave(str(path), np.concatenate(row, 1), check_contrast=False)
    return path
