"""Procedural scenes rendered by Mitsuba 3: a held-out set from an independent renderer.

    python -m pip install mitsuba        # the `mitsuba` extra; nothing else needs it
    python -m benchmarks.mitsuba_scenes --out data/mitsuba --count 24 --seed 7000
    python -m benchmarks.devset_estimate --run data/mitsuba --name mitsuba_estimate

Our sampler draws the rooms, objects, materials, camera and lights
(:func:`selfsup.scenes.sampler.sample_scene`, the first half of the scenes with one
light, the rest with two); Mitsuba 3 (``scalar_rgb``) renders them, so that none of
our own shading, shadow or anti-aliasing code makes the images. The files follow
``docs/scene-format.md`` and come in the three variants of the devset
(``../shared/devset/README.md``), each in its folder under ``--out``:

- ``direct``: the point lights' direct light only (``direct`` integrator, 16 samples
  a pixel, box filter); ``ambient`` 0;
- ``gi``: path traced with interreflections (``path``, depth 6, 256 samples); no
  ``ambient`` key (unknown);

(each light rendered alone and the images summed: see :func:`_per_light`)
- ``noisy``: the direct image with sensor noise, depth with z^2 noise, 1 mm steps and
  holes, normals refitted to that depth (planes through 5x5 windows).

Geometry (depth, normals) is Mitsuba's hit at each pixel centre, kd its ``albedo``
AOV averaged over the pixel (16 samples). Textures are bitmaps on the shapes' own
(u, v) (checker, stripes, fractal noise) instead of our solid patterns. Glossy
objects are Mitsuba's ``roughplastic`` (Beckmann, not Blinn-Phong): the file's
``shininess = 2 / alpha^2 - 2`` and ``ks = F0 / (4 alpha^2)`` are the nearest
Blinn-Phong values, so the model never fits exactly. A point emitter of radiant
intensity ``P`` is the format's ``I = P / pi``; the exposure puts the direct image's
99th percentile at the sampler's exposure, and ``gi`` and ``noisy`` keep the same
intensities.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from selfsup.scenes.io import Scene, write_scene
from selfsup.scenes.raycast import camera_rays, cast_rays
from selfsup.scenes.sampler import SamplerConfig, SceneSpec, Texture, sample_scene

GLOSSY_F0 = 0.0387  # Fresnel reflectance at normal incidence of index 1.49 (roughplastic's int_ior)


def _frame(normal: np.ndarray) -> np.ndarray:
    """A rotation ``(3, 3)`` whose third column is ``normal``."""
    n = normal / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(helper, n)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(n, a), n], 1)


def _affine(linear: np.ndarray, offset: np.ndarray):
    import mitsuba as mi

    m = np.eye(4)
    m[:3, :3], m[:3, 3] = linear, offset
    return mi.ScalarTransform4f(m.tolist())


def _room_frame(planes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The room's unit axes in the camera frame: up (the floor's normal), back (into the
    room: the back wall faces out of it) and across."""
    up, back = planes[0, 3:6], -planes[1, 3:6]
    return up, back, np.cross(up, back)


def _rectangle(centre: np.ndarray, axes: tuple[np.ndarray, np.ndarray], half: tuple[float, float],
               normal: np.ndarray) -> tuple:
    """A Mitsuba rectangle's ``to_world`` and its longer side (its texture repeats over it)."""
    linear = np.stack([axes[0] * half[0], axes[1] * half[1], normal], 1)
    return _affine(linear, centre), 2 * max(half)


def _side_wall(point: np.ndarray, normal: np.ndarray, room_size: list[float], up, back) -> tuple:
    # Through ``point`` on the floor line, from depth/2 in front of the room to its back wall.
    _, depth, height = room_size
    return _rectangle(point + back * depth / 4 + up * height / 2, (back, up), (3 * depth / 4, height / 2), normal)


def _room_rectangles(planes: np.ndarray, room_size: list[float]) -> list:
    """Finite rectangles (:func:`_rectangle`) of the sampler's infinite room planes:
    the floor, the back wall and the side walls of a ``room_size = [width, depth, height]``
    room (metres), floor and side walls extended half a depth towards the camera and
    under it, so that the open side shows no edge; no ceiling, as in the sampler."""
    width, depth, height = room_size
    up, back, across = _room_frame(planes)
    floor, wall = planes[0], planes[1]
    rectangles = [_rectangle(floor[:3] + back * depth / 4, (across, back), (width / 2, 3 * depth / 4), floor[3:6]),
                  _rectangle(wall[:3] + up * height / 2, (across, up), (width / 2, height / 2), wall[3:6])]
    return rectangles + [_side_wall(row[:3], row[3:6], room_size, up, back) for row in planes[2:]]


def _closing_rectangles(planes: np.ndarray, room_size: list[float]) -> list:
    """A ceiling over the extended floor, a front wall at its near end (behind the
    camera) and the second side wall where the sampler drew one (:func:`_rectangle`s),
    for a closed room."""
    width, depth, height = room_size
    up, back, across = _room_frame(planes)
    floor = planes[0, :3]
    closing = [_rectangle(floor + up * height + back * depth / 4, (across, back), (width / 2, 3 * depth / 4), -up),
               _rectangle(floor - back * depth / 2 + up * height / 2, (across, up), (width / 2, height / 2), back)]
    if len(planes) == 3:  # one side wall: the other, opposite it
        closing.append(_side_wall(2 * floor - planes[2, :3], -planes[2, 3:6], room_size, up, back))
    return closing


def _fractal(size: int, rng: np.random.Generator) -> np.ndarray:
    """A tileable value-noise pattern ``(size, size)`` in [0, 1], four octaves."""
    total = np.zeros((size, size))
    for octave in range(4):
        cells = 4 * 2**octave
        grid = rng.random((cells, cells))
        x = np.arange(size) * cells / size
        i0 = np.floor(x).astype(int)
        f = x - i0
        f = f * f * (3 - 2 * f)
        i1 = (i0 + 1) % cells
        rows = grid[i0][:, i0] * (1 - f)[None] + grid[i0][:, i1] * f[None]
        rows_next = grid[i1][:, i0] * (1 - f)[None] + grid[i1][:, i1] * f[None]
        total += 0.5**octave * (rows * (1 - f)[:, None] + rows_next * f[:, None])
    total -= total.min()
    return total / max(total.max(), 1e-9)


def _texture(kind: int, base: np.ndarray, alt: np.ndarray, repeats: float, rng: np.random.Generator) -> dict:
    import mitsuba as mi

    if kind == Texture.UNIFORM:
        return {"type": "rgb", "value": base.tolist()}
    size = 128
    u = (np.arange(size) + 0.5) / size
    if kind == Texture.CHECKER:
        t = ((np.floor(2 * u)[None] + np.floor(2 * u)[:, None]) % 2 == 0).astype(float)
    elif kind == Texture.STRIPES:
        along = u[None] if rng.random() < 0.5 else u[:, None]  # along u or v: a tile that repeats seamlessly
        t = np.broadcast_to(np.sin(2 * math.pi * 2 * along) > 0, (size, size)).astype(float)
    else:
        t = _fractal(size, rng)
    rgb = alt[None, None] + t[..., None] * (base - alt)[None, None]
    return {"type": "bitmap", "bitmap": mi.Bitmap(rgb.astype(np.float32)), "raw": True,
            "filter_type": "nearest" if kind != Texture.NOISE else "bilinear",
            "to_uv": mi.ScalarTransform4f().scale([repeats, repeats, 1])}


def _bsdf(texture: dict, ks: float, shininess: float) -> dict:
    if ks <= 0:
        return {"type": "twosided", "material": {"type": "diffuse", "reflectance": texture}}
    alpha = math.sqrt(2.0 / (shininess + 2.0))
    return {"type": "twosided", "material": {"type": "roughplastic", "distribution": "beckmann", "alpha": alpha,
                                              "int_ior": 1.49, "nonlinear": False, "diffuse_reflectance": texture}}


def scene_dict(spec: SceneSpec, seed: int, closed: bool = False) -> tuple[dict, np.ndarray, np.ndarray]:
    """Mitsuba's scene of ``spec``, its world frame the spec's camera frame (OpenCV), with
    the ``direct`` integrator (each render sets its samples: :func:`_render`); ``closed``
    closes the room with matte walls (albedo 0.7; :func:`_closing_rectangles`).

    Returns the scene dictionary and, per primitive (the materials' global order),
    the Blinn-Phong ``ks`` and ``shininess`` the scene file reports.
    """
    rng = np.random.default_rng(seed)
    planes = spec.prims.planes.double().numpy()
    m = spec.materials
    kind, tex_scale = m.texture.numpy(), m.texture_scale.double().numpy()
    base, alt = m.kd_base.double().numpy(), m.kd_alt.double().numpy()
    ks_in, shin_in = m.ks.double().numpy(), m.shininess.double().numpy()

    parts: list[tuple[list[dict], float]] = []  # per primitive: its shapes, texture repeats over (u, v)
    for rectangle, size in _room_rectangles(planes, spec.meta["room_size_m"]):
        parts.append(([{"type": "rectangle", "to_world": rectangle}], size))
    parts += object_shapes(spec)

    scene: dict = {"type": "scene"}
    ks_out, shin_out = np.zeros(len(parts)), np.ones(len(parts))
    for index, (shapes, extent) in enumerate(parts):
        # The bitmap holds 2 checker cells, 2 stripe periods or 4 noise cells across: one is tex_scale long.
        cells = 4 if int(kind[index]) == Texture.NOISE else 2
        repeats = max(extent / (cells * max(tex_scale[index], 1e-6)), 1.0)
        bsdf = _bsdf(_texture(int(kind[index]), base[index], alt[index], repeats, rng), ks_in[index], shin_in[index])
        if ks_in[index] > 0:
            alpha2 = 2.0 / (shin_in[index] + 2.0)
            ks_out[index], shin_out[index] = GLOSSY_F0 / (4 * alpha2), 2.0 / alpha2 - 2.0
        for part_index, shape in enumerate(shapes):
            scene[f"shape_{index}_{part_index}"] = {**shape, "bsdf": bsdf}
    if closed:
        for index, (rectangle, _) in enumerate(_closing_rectangles(planes, spec.meta["room_size_m"])):
            scene[f"closing_{index}"] = {"type": "rectangle", "to_world": rectangle,
                                         "bsdf": _bsdf({"type": "rgb", "value": [0.7, 0.7, 0.7]}, 0.0, 1.0)}
    scene.update(lights_and_sensor(spec, seed))
    scene["integrator"] = {"type": "direct"}
    return scene, ks_out, shin_out


def object_shapes(spec: SceneSpec) -> list[tuple[list[dict], float]]:
    """Mitsuba's shapes of ``spec``'s spheres, boxes and capped cylinders, per primitive (in
    that order) with the length its texture spans (a sphere's or cylinder's girth, a box's
    longest side)."""
    p = {k: getattr(spec.prims, k).double().numpy() for k in ("spheres", "boxes", "cylinders")}
    parts = [([{"type": "sphere", "center": row[:3].tolist(), "radius": float(row[3])}], 2 * math.pi * row[3])
             for row in p["spheres"]]
    for row in p["boxes"]:
        rot = row[6:15].reshape(3, 3)
        parts.append(([{"type": "cube", "to_world": _affine(rot @ np.diag(row[3:6]), row[:3])}], 2 * row[3:6].max()))
    for row in p["cylinders"]:
        centre, axis, radius, half_height = row[:3], row[3:6], float(row[6]), float(row[7])
        body = {"type": "cylinder", "p0": (centre - half_height * axis).tolist(),
                "p1": (centre + half_height * axis).tolist(), "radius": radius}
        caps = [{"type": "disk", "to_world": _affine(_frame(side * axis) @ np.diag([radius] * 3),
                                                      centre + side * half_height * axis)} for side in (-1.0, 1.0)]
        parts.append(([body, *caps], 2 * math.pi * radius))
    return parts


def lights_and_sensor(spec: SceneSpec, seed: int) -> dict:
    """The scene entries of ``spec``'s point lights (``light_<i>``; a radiant intensity of pi
    times the format's) and its camera (``sensor``: the spec's frame, field of view and size, an
    independent sampler of ``seed``, a box filter)."""
    import mitsuba as mi

    out: dict = {}
    for index, (position, intensity) in enumerate(zip(spec.light_position.double().numpy(),
                                                       spec.light_relative_intensity.double().numpy())):
        out[f"light_{index}"] = {"type": "point", "position": position.tolist(),
                                 "intensity": {"type": "rgb", "value": (math.pi * intensity).tolist()}}
    fov = 2 * math.degrees(math.atan(0.5 * spec.width / float(spec.K[0, 0])))
    out["sensor"] = {
        "type": "perspective", "fov": fov, "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
        "sampler": {"type": "independent", "seed": seed},
        "film": {"type": "hdrfilm", "width": spec.width, "height": spec.height, "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32"},
    }
    return out


def _render(scene: dict, spp: int, sampler: dict | None = None) -> np.ndarray:
    import mitsuba as mi

    scene = dict(scene)
    scene["sensor"] = dict(scene["sensor"])
    scene["sensor"]["sampler"] = sampler or {**scene["sensor"]["sampler"], "sample_count": spp}
    return np.array(mi.render(mi.load_dict(scene)), dtype=np.float64)


def _per_light(scene: dict, spp: int) -> np.ndarray:
    """The image of ``scene`` as the sum of its lights' images, each rendered alone.
    Light adds up, so this is the same image; but Mitsuba's integrators pick one
    emitter at random per sample, which with two point lights at 16 samples a
    pixel leaves the direct image as noisy as a path-traced one."""
    lights = [k for k in scene if k.startswith("light_")]
    alone = ({k: v for k, v in scene.items() if not k.startswith("light_") or k == light} for light in lights)
    return sum(_render(one, spp) for one in alone)


def _plane_normals(points: np.ndarray, valid: np.ndarray, half: int = 2) -> np.ndarray:
    """Unit normals ``(H, W, 3)`` of planes fitted (PCA) to the valid points of each
    ``(2 half + 1)^2`` window, facing the camera; zero where missing or too few points.
    The devset's recipe, written out here rather than taken from
    :func:`render.geometry.plane_normals`: the test files must not share the estimator's code."""
    H, W, _ = points.shape
    pad = np.pad(points, ((half, half), (half, half), (0, 0)))
    vpad = np.pad(valid, half).astype(float)
    count = np.zeros((H, W))
    s1 = np.zeros((H, W, 3))
    s2 = np.zeros((H, W, 3, 3))
    for di in range(2 * half + 1):
        for dj in range(2 * half + 1):
            q = pad[di:di + H, dj:dj + W]
            w = vpad[di:di + H, dj:dj + W]
            count += w
            s1 += w[..., None] * q
            s2 += w[..., None, None] * q[..., :, None] * q[..., None, :]
    mean = s1 / np.maximum(count, 1)[..., None]
    cov = s2 / np.maximum(count, 1)[..., None, None] - mean[..., :, None] * mean[..., None, :]
    _, vectors = np.linalg.eigh(cov)
    n = vectors[..., 0]
    n = np.where((np.sum(n * points, -1) > 0)[..., None], -n, n)
    return np.where((valid & (count >= 4))[..., None], n, 0.0)


def _pixel_rays(K: np.ndarray, H: int, W: int) -> np.ndarray:
    """Directions ``(H, W, 3)`` through the pixel centres with ``z = 1``
    (:func:`selfsup.scenes.raycast.camera_rays`): a depth times its ray is the point."""
    return camera_rays(torch.as_tensor(K, dtype=torch.float64), H, W).numpy().reshape(H, W, 3)


def _diagonal(points: np.ndarray) -> float:
    """The format's ``scene_scale``: the diagonal of the bounding box of ``points (N, 3)``."""
    return float(np.linalg.norm(points.max(0) - points.min(0)))


def _sensor_noise(image: np.ndarray, depth: np.ndarray, normals: np.ndarray, K: np.ndarray,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The devset's sensor model (``../shared/devset`` noisy files' notes): image noise
    ``sqrt(1.44e-4 m I + (0.006 m)^2)`` with ``m`` the mean image; depth ``+ N(0, 0.0012 z^2
    + 0.002)``, 1 mm steps, holes at depth jumps, grazing views and 2% random pixels;
    normals refitted to the noisy depth. Returns the image, depth, normals and the
    points ``(H, W, 3)`` of that depth."""
    m = image.mean()
    sigma = np.sqrt(1.44e-4 * m * image + (0.006 * m) ** 2)
    noisy_image = np.clip(image + sigma * rng.standard_normal(image.shape), 0, None)
    valid = depth > 0
    z = depth + (0.0012 * depth**2 + 0.002) * rng.standard_normal(depth.shape)
    z = np.round(z / 0.001) * 0.001
    H, W = depth.shape
    pad = np.pad(np.where(valid, depth, np.nan), 1, constant_values=np.nan)
    steps = np.stack([np.abs(pad[i:i + H, j:j + W] - depth) for i in range(3) for j in range(3)])
    jump = np.nan_to_num(steps).max(0) > 0.1 * depth  # a step to a neighbour; a missing one is none
    rays = _pixel_rays(K, H, W)
    view = -rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    grazing = np.sum(normals * view, -1) < math.cos(math.radians(85))
    keep = valid & ~jump & ~grazing & (rng.random(depth.shape) >= 0.02) & (z > 0)
    z = np.where(keep, z, 0.0)
    points = z[..., None] * rays
    return noisy_image, z, _plane_normals(points, keep), points


def render_variants(spec: SceneSpec, scene_id: str, closed: bool = False, exposure: float | None = None,
                    variants: tuple[str, ...] = ("direct", "gi", "noisy"), noise_seed: int | None = None
                    ) -> dict[str, Scene]:
    """The ``direct``, ``gi`` and ``noisy`` scene files of ``spec`` (Mitsuba's variant must
    be set), or those of ``variants``; ``closed``: see :func:`scene_dict`. ``exposure``:
    the image's scale (None: the spec's exposure over the 99th percentile of the direct
    light; a sequence keeps its first frame's); ``noise_seed``: the sensor noise's draw
    (None: from the spec's seed; a sequence's frames each draw their own)."""
    import mitsuba as mi

    seed = spec.seed % (2**31)
    scene, ks_prim, shin_prim = scene_dict(spec, seed, closed)
    aov = {"type": "aov", "aovs": "pos:position,nn:sh_normal,alb:albedo"}
    centre = {"type": "stratified", "sample_count": 1, "jitter": False}
    geometry = _render({**scene, "integrator": aov}, 1, centre)
    # Channels: position (3), shading normal (3), albedo (3).
    albedo = _render({**scene, "integrator": aov}, 16)[..., 6:9]
    points, normals = geometry[..., 0:3], geometry[..., 3:6]
    valid = np.linalg.norm(normals, axis=-1) > 0.5
    depth = np.where(valid, points[..., 2], 0.0)
    normals = np.where((np.sum(normals * points, -1) > 0)[..., None], -normals, normals) * valid[..., None]
    # Which primitive each pixel centre sees, to report its Blinn-Phong ks and shininess:
    # our own ray caster, used for this lookup only (the images and geometry are Mitsuba's).
    hit = cast_rays(spec.prims.to(torch.float64), torch.zeros(spec.height * spec.width, 3, dtype=torch.float64),
                    camera_rays(spec.K.double(), spec.height, spec.width))
    primitive = hit.primitive.clamp_min(0).reshape(spec.height, spec.width).numpy()
    # Where Mitsuba met something else (a closing wall), that surface is matte.
    ours = (hit.primitive >= 0).reshape(spec.height, spec.width).numpy() & (
        np.abs(hit.t.reshape(spec.height, spec.width).numpy() - depth) <= 1e-3 * np.maximum(depth, 1e-6))
    ks = np.where(valid & ours, ks_prim[primitive], 0.0)
    shininess = np.where(valid & ours, shin_prim[primitive], 1.0)

    direct = _per_light(scene, 16)
    gi = _per_light({**scene, "integrator": {"type": "path", "max_depth": 6}}, 256) if "gi" in variants else None
    brightest = direct.max(-1)[valid]
    if exposure is None:
        exposure = spec.exposure / max(float(np.quantile(brightest, 0.99)), 1e-6)
    K = spec.K.double().numpy()
    meta = {"falloff": "inverse_square", "n_lights": int(spec.light_position.shape[0]), "seed": spec.seed,
            "renderer": f"mitsuba {mi.__version__} {mi.variant()}", **spec.meta, "closed_room": closed,
            "specular": "roughplastic (Beckmann, int_ior 1.49): shininess = 2/alpha^2-2, ks = F0/(4 alpha^2), F0=0.0387",
            "light_intensity": "I = P/pi, P = Mitsuba point-emitter radiant intensity (RGB)"}

    def scene_file(image: np.ndarray, variant: str, **extra) -> Scene:
        def t(x):
            return torch.as_tensor(np.asarray(x), dtype=torch.float32)

        fields = dict(image=t(image * exposure * valid[..., None]), depth=t(depth), K=t(K), kd=t(albedo * valid[..., None]),
                      ks=t(ks[..., None]), shininess=t(shininess), normals=t(normals), ambient=t(np.zeros(3)),
                      light_pos=spec.light_position.float(), light_intensity=(spec.light_relative_intensity * exposure).float(),
                      scene_scale=t(_diagonal(points[valid])))
        fields.update({k: (t(v) if v is not None else None) for k, v in extra.items()})
        return Scene(meta={**meta, "id": f"{scene_id}_{variant}", "generator": f"mitsuba3-{variant}"}, **fields)

    rng = np.random.default_rng(seed + 1 if noise_seed is None else noise_seed)
    noisy_image, noisy_depth, noisy_normals, noisy_points = _sensor_noise(direct * exposure * valid[..., None], depth,
                                                                          normals, K, rng)
    made = {
        "direct": lambda: scene_file(direct, "direct"),
        "gi": lambda: scene_file(gi, "gi", ambient=None),
        "noisy": lambda: scene_file(noisy_image / exposure, "noisy", depth=noisy_depth, normals=noisy_normals,
                                    scene_scale=_diagonal(noisy_points[noisy_depth > 0])),
    }
    return {variant: made[variant]() for variant in variants}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="data/mitsuba")
    parser.add_argument("--count", type=int, default=24, help="scenes; the first half one light, the rest two")
    parser.add_argument("--seed", type=int, default=7000)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--closed", action="store_true", help="close the room: a ceiling, a wall behind the camera, both side walls")
    args = parser.parse_args()
    try:
        import mitsuba as mi
    except ImportError:
        parser.exit(2, "mitsuba_scenes needs Mitsuba 3: python -m pip install mitsuba\n")
    mi.set_variant("scalar_rgb")
    config = SamplerConfig(height=args.height, width=args.width)
    for variant in ("direct", "gi", "noisy"):
        (Path(args.out) / variant).mkdir(parents=True, exist_ok=True)
    for index in range(args.count):
        n_lights = 1 if index < (args.count + 1) // 2 else 2
        spec = sample_scene(args.seed * 1_000_003 + index, config, n_lights=n_lights)
        for variant, scene in render_variants(spec, f"mitsuba_{args.seed}_{index:03d}", args.closed).items():
            write_scene(Path(args.out) / variant / f"scene_{index:03d}.npz", scene)
        print(json.dumps({"scene": index, "lights": n_lights, "objects": spec.meta["objects"]}), flush=True)


if __name__ == "__main__":
    main()
