"""Random indoor-like scenes of analytic primitives: room, objects, materials, lights, camera.

A sampled :class:`SceneSpec` is everything the exact renderer
(:mod:`selfsup.scenes.exact`) needs; nothing here renders. Everything is drawn
from one ``torch.Generator``, so a seed fixes the scene.

World frame while building: y up, floor ``y = 0``, the room spans
``x in [-W/2, W/2]``, ``z in [0, D]`` with the back wall at ``z = D`` and the side
open towards the camera (``z < 0``). The spec is returned in the camera frame
(OpenCV: x right, y down, z forward) that the scene format uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from selfsup.scenes.raycast import Primitives

__all__ = ["SamplerConfig", "SceneSpec", "Materials", "Texture", "sample_scene", "signed_distance"]


class Texture:
    """Albedo pattern kinds (ints so they live in a tensor)."""

    UNIFORM, CHECKER, STRIPES, NOISE = 0, 1, 2, 3


@dataclass
class SamplerConfig:
    """Distributions of the scene sampler (mirrors ``configs/data/*.yaml``).

    Lengths in metres; ranges are ``[low, high]``. ``n_lights_probs[i]`` is the
    probability of ``i + 1`` lights. ``scale_range`` multiplies the whole scene
    (room, objects, lights) so that no absolute size is assumed downstream.
    """

    height: int = 128
    width: int = 128
    fov_x_deg: tuple[float, float] = (50.0, 75.0)
    room_width: tuple[float, float] = (3.0, 5.5)
    room_depth: tuple[float, float] = (3.0, 5.5)
    room_height: tuple[float, float] = (2.4, 3.2)
    two_side_walls_prob: float = 0.5
    n_objects: tuple[int, int] = (2, 8)
    n_lights_probs: tuple[float, ...] = (1.0,)
    light_margin: float = 0.3  # metres, to every surface, after scaling
    specular_prob: float = 0.35
    ks_range: tuple[float, float] = (0.1, 0.7)
    shininess_range: tuple[float, float] = (5.0, 200.0)
    ambient_zero_prob: float = 0.3
    ambient_range: tuple[float, float] = (0.0, 0.15)
    exposure_range: tuple[float, float] = (0.6, 1.1)
    scale_range: tuple[float, float] = (0.7, 1.4)
    light_power_range: tuple[float, float] = (1 / 3, 1.0)  # each light's power (times its distance^2), relative
    studio_prob: float = 0.0  # share of scenes that are objects photographed in the dark (selfsup.scenes.studio), not rooms
    panel_prob: float = 0.0  # share of rooms lit by ceiling panels (selfsup.scenes.studio.scene_spec), not point lights

    def __post_init__(self):
        # Bad settings are named here, not met as a NaN probability or an empty room deep in sampling.
        if not (isinstance(self.height, int) and isinstance(self.width, int) and self.height >= 1 and self.width >= 1):
            raise ValueError(f"sampler height and width must be integers >= 1, got {self.height!r} x {self.width!r}")
        probs = tuple(float(p) for p in self.n_lights_probs)
        if not probs or not all(math.isfinite(p) and p >= 0 for p in probs) or sum(probs) <= 0:
            raise ValueError(f"sampler n_lights_probs must be finite, >= 0 and not all 0, got {list(self.n_lights_probs)}")
        self.n_lights_probs = probs
        ranges = {"fov_x_deg": (0, 180), "room_width": (0, math.inf), "room_depth": (0, math.inf),
                  "room_height": (0, math.inf), "ks_range": (0, math.inf), "shininess_range": (0, math.inf),
                  "ambient_range": (0, math.inf), "exposure_range": (0, math.inf), "scale_range": (0, math.inf),
                  "light_power_range": (0, math.inf)}
        for name, (low, high) in ranges.items():
            a, b = (float(x) for x in getattr(self, name))
            positive = name not in ("ks_range", "ambient_range")  # these two may reach 0
            if not (low <= a <= b < high and (a > low or not positive)):
                raise ValueError(f"sampler {name} must be a range [low, high] with {low} {'<' if positive else '<='} "
                                 f"low <= high < {high}, got {list(getattr(self, name))}")
        a, b = self.n_objects
        if not (0 <= a <= b):
            raise ValueError(f"sampler n_objects must be a range [low, high] with 0 <= low <= high, got {[a, b]}")
        for name in ("two_side_walls_prob", "specular_prob", "ambient_zero_prob", "studio_prob", "panel_prob"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"sampler {name} must be a probability in [0, 1], got {getattr(self, name)}")
        if not self.light_margin >= 0:
            raise ValueError(f"sampler light_margin must be >= 0 metres, got {self.light_margin}")


@dataclass(frozen=True)
class Materials:
    """Per-primitive material tables, global order (planes, spheres, boxes, cylinders,
    as in :func:`raycast.cast_rays`), of one scene or of a batch of scenes.

    Attributes:
        kd_base, kd_alt: ``(P, 3)`` albedo colours.
        texture: ``(P,)`` int, a :class:`Texture` kind; texture_scale ``(P,)`` metres;
            texture_dir ``(P, 3)`` unit (stripes).
        ks: ``(P,)``; shininess: ``(P,)``.
    """

    kd_base: Tensor
    kd_alt: Tensor
    texture: Tensor
    texture_scale: Tensor
    texture_dir: Tensor
    ks: Tensor
    shininess: Tensor


@dataclass
class SceneSpec:
    """One sampled scene in the camera frame.

    Attributes:
        prims: the shapes (planes, spheres, boxes, cylinders), float32.
        materials: their :class:`Materials`.
        K: ``(3, 3)``; height, width: image size.
        light_position, light_relative_intensity: ``(L, 3)``; the exposure is fixed
            at render time. ambient_relative: ``(3,)``.
        meta: free notes for the scene file.
    """

    prims: Primitives
    materials: Materials
    K: Tensor
    height: int
    width: int
    light_position: Tensor
    light_relative_intensity: Tensor
    ambient_relative: Tensor
    exposure: float
    seed: int
    meta: dict = field(default_factory=dict)


def _uniform(gen: torch.Generator, low: float, high: float, *shape: int) -> Tensor:
    return low + (high - low) * torch.rand(shape or (1,), generator=gen, dtype=torch.float64)


def _us(gen: torch.Generator, *bounds) -> list[float]:
    """A number uniform in each of ``bounds`` in turn, from one draw of that many doubles
    (the generator yields the same doubles one after another as in single draws), computed
    in Python floats as ``float(_uniform(...))`` would (the same float64 operations)."""
    draws = torch.rand(len(bounds), generator=gen, dtype=torch.float64).tolist()
    return [float(low) + (float(high) - float(low)) * u for (low, high), u in zip(bounds, draws)]


def _u(gen: torch.Generator, bounds) -> float:
    return _us(gen, bounds)[0]


def _rot_y(angle: float) -> Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)


def _box_sdf(p: Tensor, boxes: Tensor) -> Tensor:
    # Exact signed distances to oriented boxes; p (N, 3), boxes (X, 15) -> (N, X).
    local = (p - boxes[:, None, :3]) @ boxes[:, 6:15].reshape(-1, 3, 3)  # (X, N, 3)
    q = local.abs() - boxes[:, None, 3:6]
    return (q.clamp_min(0).norm(dim=-1) + q.max(-1).values.clamp_max(0)).T


def _cylinder_sdf(p: Tensor, cylinders: Tensor) -> Tensor:
    # Exact signed distances to capped cylinders; p (N, 3), cylinders (C, 8) -> (N, C).
    rel = p - cylinders[:, None, :3]  # (C, N, 3)
    axis = cylinders[:, None, 3:6]
    along = (rel @ cylinders[:, 3:6, None])[..., 0]
    radial = (rel - along[..., None] * axis).norm(dim=-1)
    q = torch.stack([radial - cylinders[:, 6:7], along.abs() - cylinders[:, 7:8]], -1)
    return (q.clamp_min(0).norm(dim=-1) + q.max(-1).values.clamp_max(0)).T


def signed_distance(prims: Primitives, points: Tensor, include_planes: bool = True) -> Tensor:
    """Smallest signed distance ``(N,)`` from ``points (N, 3)`` to the shapes (< 0 inside one).

    Planes count as half-spaces on the side their normal points away from.
    """
    parts = [torch.full(points.shape[:1] + (1,), float("inf"), dtype=points.dtype)]
    if include_planes and prims.planes.shape[0]:
        parts.append(((points - prims.planes[:, None, :3]) @ prims.planes[:, 3:6, None])[..., 0].T)
    if prims.spheres.shape[0]:
        parts.append(((points - prims.spheres[:, None, :3]).norm(dim=-1) - prims.spheres[:, 3:4]).T)
    if prims.boxes.shape[0]:
        parts.append(_box_sdf(points, prims.boxes))
    if prims.cylinders.shape[0]:
        parts.append(_cylinder_sdf(points, prims.cylinders))
    return torch.cat(parts, 1).amin(1)


class _Objects:
    """Objects as world-frame rows while the room is built."""

    def __init__(self):
        self.spheres: list[list[float]] = []
        self.boxes: list[list[float]] = []
        self.cylinders: list[list[float]] = []
        self.footprints: list[tuple[float, float, float]] = []  # x, z, radius on the floor
        self.tops: list[tuple[float, float, float, float]] = []  # x, z, top y, free radius
        self.names: list[str] = []

    def free(self, x: float, z: float, r: float) -> bool:
        return all((x - fx) ** 2 + (z - fz) ** 2 > (r + fr + 0.05) ** 2 for fx, fz, fr in self.footprints)

    def box(self, centre, half, angle: float = 0.0) -> None:
        self.boxes.append([*centre, *half, *_rot_y(angle).reshape(-1).tolist()])


def _place_object(gen: torch.Generator, objs: _Objects, room_w: float, room_d: float) -> None:
    kind = int(torch.randint(0, 6, (1,), generator=gen))
    # Each try draws its position and the sizes it needs at once, in the order they are used.
    x_range, z_range = (-room_w / 2 + 0.35, room_w / 2 - 0.35), (0.9, room_d - 0.35)
    for _ in range(12):
        if kind == 0:  # box on the floor
            x, z, *half = _us(gen, x_range, z_range, (0.1, 0.45), (0.1, 0.5), (0.1, 0.45))
            radius = math.hypot(half[0], half[2])
            if objs.free(x, z, radius):
                objs.box([x, half[1], z], half, _u(gen, (0, math.pi)))
                objs.footprints.append((x, z, radius))
                objs.tops.append((x, z, 2 * half[1], min(half[0], half[2])))
                objs.names.append("box")
                return
        elif kind == 1:  # sphere resting on the floor
            x, z, r = _us(gen, x_range, z_range, (0.1, 0.45))
            if objs.free(x, z, r):
                objs.spheres.append([x, r, z, r])
                objs.footprints.append((x, z, r))
                objs.names.append("sphere")
                return
        elif kind == 2:  # upright cylinder
            x, z, r, h = _us(gen, x_range, z_range, (0.08, 0.3), (0.1, 0.6))
            if objs.free(x, z, r):
                objs.cylinders.append([x, h, z, 0, 1, 0, r, h])
                objs.footprints.append((x, z, r))
                objs.tops.append((x, z, 2 * h, r))
                objs.names.append("cylinder")
                return
        elif kind == 3:  # pedestal table: thin top on one column
            x, z, hx, hz, top = _us(gen, x_range, z_range, (0.3, 0.7), (0.25, 0.5), (0.5, 0.9))
            radius = math.hypot(hx, hz)
            if objs.free(x, z, radius):
                thick, angle = _us(gen, (0.02, 0.04), (0, math.pi))
                objs.box([x, top - thick, z], [hx, thick, hz], angle)
                objs.cylinders.append([x, (top - 2 * thick) / 2, z, 0, 1, 0, 0.05, (top - 2 * thick) / 2])
                objs.footprints.append((x, z, radius))
                objs.tops.append((x, z, top, min(hx, hz)))
                objs.names.append("table")
                return
        elif kind == 4:  # shelf on the back wall
            x, z, hx, hz, y, thick = _us(gen, x_range, z_range, (0.3, 0.8), (0.1, 0.18), (0.6, 1.7), (0.015, 0.03))
            objs.box([x, y, room_d - hz], [hx, thick, hz])
            objs.tops.append((x, room_d - hz, y + thick, min(hx, hz)))
            objs.names.append("shelf")
            return
        else:  # something on top of an earlier object, else a sphere on the floor
            _us(gen, x_range, z_range)  # a position, unused, as every try draws
            if objs.tops:
                index = int(torch.randint(0, len(objs.tops), (1,), generator=gen))
                tx, tz, ty, free_r = objs.tops.pop(index)
                r = min(_u(gen, (0.06, 0.2)), free_r)
                if r > 0.04:
                    if torch.rand(1, generator=gen) < 0.5:
                        objs.spheres.append([tx, ty + r, tz, r])
                    else:
                        objs.box([tx, ty + r, tz], [r, r, r], _u(gen, (0, math.pi)))
                    objs.names.append("object_on_object")
                    return
            kind = 1


def _camera_rotation(forward: Tensor) -> Tensor:
    # Rows: camera x (right), y (down), z (forward) in world coordinates (world y up).
    z = forward / forward.norm()
    down = torch.tensor([0.0, -1.0, 0.0], dtype=forward.dtype)
    x = torch.linalg.cross(down, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    return torch.stack([x, y, z])


def _material(gen: torch.Generator, n: int, config: SamplerConfig, room_planes: int):
    base = _uniform(gen, 0.15, 0.9, n, 3)
    alt = (base * _uniform(gen, 0.3, 0.8, n, 1)).clamp(0.02, 1.0)
    texture = torch.randint(0, 4, (n,), generator=gen)
    scale = torch.exp(_uniform(gen, math.log(0.08), math.log(0.6), n))
    direction = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    direction = direction / direction.norm(dim=-1, keepdim=True)
    specular = torch.rand(n, generator=gen, dtype=torch.float64) < config.specular_prob
    specular[:room_planes] &= torch.rand(room_planes, generator=gen) < 0.3  # rooms mostly matte
    ks = torch.where(specular, _uniform(gen, *config.ks_range, n), torch.zeros(n, dtype=torch.float64))
    shininess = torch.exp(_uniform(gen, math.log(config.shininess_range[0]), math.log(config.shininess_range[1]), n))
    return base, alt, texture, scale, direction, ks, shininess


def _sample_lights(gen: torch.Generator, config: SamplerConfig, world: Primitives, n_lights: int | None,
                   light_position_world: Tensor | None, scale: float, room: tuple[float, float, float]) -> Tensor:
    """Room-frame light positions ``(L, 3)``: inside the room, ``light_margin`` from every
    surface, never inside an object; ``n_lights`` drawn from ``n_lights_probs`` when None."""
    room_w, room_d, room_h = room
    if n_lights is None:
        probs = torch.tensor(config.n_lights_probs, dtype=torch.float64)
        n_lights = int(torch.multinomial(probs / probs.sum(), 1, generator=gen)) + 1
    margin = config.light_margin / scale  # the margin is in final metres; the room is scaled below
    lo = torch.tensor([-room_w / 2 + margin, margin + 0.5, margin], dtype=torch.float64)
    hi = torch.tensor([room_w / 2 - margin, room_h - margin, room_d - margin], dtype=torch.float64)
    if light_position_world is not None:
        lights = lo + light_position_world.to(torch.float64) * (hi - lo)
        lights = lights[signed_distance(world, lights) > margin]
        if lights.shape[0] != light_position_world.shape[0]:
            raise ValueError("a requested light position falls inside or too close to an object")
        return lights
    chosen = []
    while len(chosen) < n_lights:
        candidates = lo + torch.rand(64, 3, generator=gen, dtype=torch.float64) * (hi - lo)
        ok = signed_distance(world, candidates) > margin
        chosen.extend(candidates[ok][: n_lights - len(chosen)])
    return torch.stack(chosen)


def sample_scene(seed: int, config: SamplerConfig | None = None, n_lights: int | None = None,
                 light_position_world: Tensor | None = None) -> SceneSpec:
    """Draw one scene from ``seed`` (same seed, same scene).

    Args:
        seed: seeds a private ``torch.Generator``; the global RNG is untouched.
        config: the distributions; defaults to :class:`SamplerConfig`.
        n_lights: force the number of lights (else drawn from ``n_lights_probs``).
        light_position_world: ``(L, 3)`` room-frame positions in ``[0, 1]^3``
            (x across, y up, z into the room) to use instead of random ones;
            used by the protocol set to spread lights around a fixed scene.
    """
    config = config or SamplerConfig()
    gen = torch.Generator().manual_seed(int(seed))
    log_scale, room_w, room_d, room_h = _us(gen, tuple(math.log(x) for x in config.scale_range), config.room_width,
                                            config.room_depth, config.room_height)
    scale = math.exp(log_scale)

    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    planes = [[0, 0, 0, *up.tolist()], [0, 0, room_d, 0, 0, -1]]
    both_walls = bool(torch.rand(1, generator=gen) < config.two_side_walls_prob)
    left_first = bool(torch.rand(1, generator=gen) < 0.5)
    if both_walls or left_first:
        planes.append([-room_w / 2, 0, 0, 1, 0, 0])
    if both_walls or not left_first:
        planes.append([room_w / 2, 0, 0, -1, 0, 0])

    objs = _Objects()
    count = int(torch.randint(config.n_objects[0], config.n_objects[1] + 1, (1,), generator=gen))
    for _ in range(count):
        _place_object(gen, objs, room_w, room_d)

    world = Primitives(
        planes=torch.tensor(planes, dtype=torch.float64),
        spheres=torch.tensor(objs.spheres, dtype=torch.float64).reshape(-1, 4),
        boxes=torch.tensor(objs.boxes, dtype=torch.float64).reshape(-1, 15),
        cylinders=torch.tensor(objs.cylinders, dtype=torch.float64).reshape(-1, 8),
    )

    lights = _sample_lights(gen, config, world, n_lights, light_position_world, scale, (room_w, room_d, room_h))
    n_lights = lights.shape[0]

    # Camera at the open side, looking in, slightly down.
    cx, cy, cz, tx, ty, tz, fov = _us(gen, (-0.3, 0.3), (1.0, 1.8), (-0.6, 0.3), (-0.2, 0.2), (0.2, 0.8), (0.55, 0.85),
                                      config.fov_x_deg)
    camera = torch.tensor([cx * room_w, cy, cz], dtype=torch.float64)
    target = torch.tensor([tx * room_w, ty, tz * room_d], dtype=torch.float64)
    rot = _camera_rotation(target - camera)

    def to_cam(p: Tensor) -> Tensor:
        return (p - camera) @ rot.T

    prims = Primitives(
        planes=torch.cat([to_cam(world.planes[:, :3]), world.planes[:, 3:6] @ rot.T], 1),
        spheres=torch.cat([to_cam(world.spheres[:, :3]), world.spheres[:, 3:4]], 1),
        boxes=torch.cat([to_cam(world.boxes[:, :3]), world.boxes[:, 3:6],
                         (rot[None] @ world.boxes[:, 6:15].reshape(-1, 3, 3)).reshape(-1, 9)], 1),
        cylinders=torch.cat([to_cam(world.cylinders[:, :3]), world.cylinders[:, 3:6] @ rot.T, world.cylinders[:, 6:8]], 1),
    )
    # One global scale so that downstream code cannot rely on absolute sizes.
    prims.planes[:, :3] *= scale
    prims.spheres *= scale
    prims.boxes[:, :6] *= scale
    prims.cylinders[:, :3] *= scale
    prims.cylinders[:, 6:8] *= scale
    light_cam = to_cam(lights) * scale

    n_prims = sum(t.shape[0] for t in (prims.planes, prims.spheres, prims.boxes, prims.cylinders))
    base, alt, texture, tex_scale, tex_dir, ks, shininess = _material(gen, n_prims, config, len(planes))
    f = 0.5 * config.width / math.tan(math.radians(fov) / 2)
    K = torch.tensor([[f, 0, (config.width - 1) / 2], [0, f, (config.height - 1) / 2], [0, 0, 1]], dtype=torch.float64)
    # Light colours near white, each light's power drawn log-uniformly in light_power_range
    # (by default within a factor 3 of the others).
    tint = _uniform(gen, 0.75, 1.0, n_lights, 3)
    low, high = (math.log(x) for x in config.light_power_range)
    power = torch.exp(_uniform(gen, low, high, n_lights, 1)) * (light_cam.norm(dim=-1, keepdim=True) ** 2)
    ambient = torch.zeros(3, dtype=torch.float64)
    if torch.rand(1, generator=gen) >= config.ambient_zero_prob:
        ambient = _u(gen, config.ambient_range) * _uniform(gen, 0.8, 1.0, 3)
    return SceneSpec(
        prims=prims.to(torch.float32),
        materials=Materials(kd_base=base.float(), kd_alt=alt.float(), texture=texture,
                            texture_scale=(tex_scale * scale).float(), texture_dir=tex_dir.float(), ks=ks.float(),
                            shininess=shininess.float()),
        K=K.float(), height=config.height, width=config.width,
        light_position=light_cam.float(), light_relative_intensity=(tint * power).float(),
        ambient_relative=ambient.float(), exposure=_u(gen, config.exposure_range), seed=int(seed),
        meta={"room_size_m": [room_w * scale, room_d * scale, room_h * scale], "objects": objs.names,
              "side_walls": "both" if both_walls else ("left" if left_first else "right"), "fov_x_deg": fov},
    )
