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
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from selfsup.scenes.camera import CameraModel, camera_capture, with_area_lights, write_capture_frame
from selfsup.scenes.capture import capture_frames, read_capture
from selfsup.scenes.exact import render_spec
from selfsup.scenes.integration import integrated_depth
from selfsup.scenes.io import Scene
from selfsup.scenes.raycast import Primitives
from selfsup.scenes.sampler import Materials, SamplerConfig, SceneSpec, Texture, sample_scene

__all__ = ["studio_spec", "sphere_centre", "lamp_angle_deg", "PATTERNS", "ARRANGEMENTS", "DEPTHS", "HARD_PAINTS", "drawn_studio_spec",
           "scene_spec", "PHOTO_CAMERA", "photograph", "PANEL_SIZE", "PANEL_POINTS"]


# The paints of :func:`studio_spec`: one albedo, stripes of a second one (hard edges, as
# painted bands), or fractal noise between the two (an albedo that changes smoothly).
PATTERNS = {"uniform": Texture.UNIFORM, "stripes": Texture.STRIPES, "noise": Texture.NOISE}
# Where :func:`studio_spec` sets the box and the cylinder beside the sphere.
ARRANGEMENTS = ("apart", "overlapping")
# The depth :func:`photograph` writes: the render's, or integrated from its normals.
DEPTHS = ("rendered", "integrated")

# :func:`studio_spec`'s analogues of the real objects that are hard (issue "Right on real
# photographs of objects"): parts that shadow each other under gold, glossy paint; dark metal
# with a sharp highlight; grey stripes painted across the shapes.
HARD_PAINTS = {
    "gold paint, parts shadowing each other": dict(albedo=(0.75, 0.55, 0.2), ks=0.6, shininess=30.0),
    "dark metal": dict(albedo=(0.15, 0.15, 0.15), ks=0.9, shininess=150.0),
    "grey stripes painted across the shapes": dict(pattern="stripes", ks=0.1),
}


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
                pattern_scale: float | None = None, arrangement: str = "apart") -> SceneSpec:
    """A sphere of ``radius`` metres ``distance`` metres before the camera (and, with
    ``others``, a box and an upright cylinder beside it), of one ``albedo`` and gloss
    (``ks``, ``shininess``), against a black background, in a camera of ``fov_x_deg``.

    ``pattern``: the paint, :data:`PATTERNS`: ``uniform`` (``albedo``), ``stripes`` (bands of
    ``albedo`` and ``second_albedo``, ``pattern_scale`` metres a pair, default ``radius``;
    across the objects' surfaces, as stripes painted on a figure) or ``noise`` (fractal noise
    between the two: an albedo that changes smoothly). ``second_albedo`` defaults to 55% of
    ``albedo`` (a grey paint on a white one).

    ``arrangement`` (with ``others``): ``apart`` (the box left of the sphere and a little behind
    it, the cylinder right of it and behind: each its own region of the view) or
    ``overlapping`` (the box half in front of the sphere's left, the cylinder half behind its
    right: one region, parts that hide each other, as a figure's; its depth integrated from its
    normals, :func:`photograph`, is then a smooth sheet over the hidden jumps).

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
    if arrangement not in ARRANGEMENTS:
        raise ValueError(f"arrangement must be one of {ARRANGEMENTS}, got {arrangement!r}")
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
        # Overlapping: the box 1.1 radii left of the sphere's centre and 1.3 before it, the cylinder
        # 1.0 right and 0.9 behind.
        box_x, box_z, cylinder_x, cylinder_z = (-2.6, 1.2, 2.5, 0.8) if arrangement == "apart" else (-1.1, -1.3, 1.0, 0.9)
        box_centre = centre + torch.tensor([box_x * radius, radius - half[1], box_z * radius], dtype=torch.float64)
        boxes = torch.cat([box_centre, half, rotation.reshape(-1)])[None]
        cylinders = torch.tensor([[cylinder_x * radius, 0.0, distance + cylinder_z * radius, 0.0, 1.0, 0.0, 0.6 * radius,
                                   radius]], dtype=torch.float64)
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


# The camera of a photometric-stereo set: auto exposure, sRGB, 8 bits, PNG, millimetre depth.
PHOTO_CAMERA = CameraModel(key=(0.12, 0.3), white_balance=False, vignetting=0.0, jpeg_quality=None,
                           misregistration_px=0.0, disparity_step=0.0, depth_bumps=0.0, edge_holes=0.0, random_holes=0.0)


def photograph(folder: str | Path, spec: SceneSpec, seed: int = 0, depth: str = "rendered",
               normals: bool = False) -> Scene:
    """``spec`` rendered exactly, through :data:`PHOTO_CAMERA` (its draw ``seed``), written as a
    capture folder ``folder`` (docs/scene-format.md) and read back: the frame as a user's file.
    ``depth``: ``rendered`` (the true depth) or ``integrated`` (integrated from the true normals,
    :func:`selfsup.scenes.integration.integrated_depth`, as the DiLiGenT objects' depth was made).
    ``normals``: the true normals written beside it (``normals/frame.npy``), as a
    photometric-stereo set gives them."""
    if depth not in DEPTHS:
        raise ValueError(f"depth must be one of {DEPTHS}, got {depth!r}")
    rendered = render_spec(spec).scene
    z = rendered.depth if depth == "rendered" else integrated_depth(rendered.normals, rendered.depth, rendered.K)
    shot = camera_capture(rendered.image, z, rendered.K, PHOTO_CAMERA, seed=seed)
    write_capture_frame(Path(folder), "frame", shot)
    if normals:
        (Path(folder) / "normals").mkdir(exist_ok=True)
        np.save(Path(folder) / "normals" / "frame.npy", rendered.normals.numpy())
    return read_capture(capture_frames(folder)[0])


def sphere_centre(spec: SceneSpec) -> Tensor:
    """The sphere's centre ``(3,)`` of a :func:`studio_spec` (the point light directions are judged from)."""
    return spec.prims.spheres[0, :3]


def lamp_angle_deg(record: dict, spec: SceneSpec, direction) -> float:
    """Degrees between the lamp's true ``direction`` (3,) and the direction from
    :func:`sphere_centre` to an estimate ``record``'s first light (an unsupported one where it
    found none); 90 where it has no light at all. How the studio's frames are scored."""
    lights = record["lights"] or record.get("unsupported_lights") or []
    if not lights:
        return 90.0
    v = np.asarray(lights[0]["position"]) - sphere_centre(spec).numpy()
    d = np.asarray(direction, dtype=np.float64)
    return math.degrees(math.acos(float(np.clip(v @ d / (np.linalg.norm(v) * np.linalg.norm(d)), -1, 1))))


# How :func:`drawn_studio_spec` draws a photometric-stereo frame (DiLiGenT-like: one object in a
# narrow view, one lamp in front of it). Angles in degrees, lengths in sphere radii.
STUDIO_FOV_DEG = (8.0, 35.0)        # the camera's horizontal field, log-uniform
STUDIO_FILL = (0.5, 0.9)            # the objects' width over the view's at their distance
STUDIO_DISTANCE_M = (0.5, 3.0)      # the sphere's distance from the camera (a depth sensor's range)
STUDIO_LIGHT_CONE_DEG = 75.0        # the lamp within this angle of the direction to the camera
STUDIO_LIGHT_DISTANCE = (5.0, 15.0)  # radii from the sphere's centre, log-uniform (outside the box and cylinder)
STUDIO_PATTERN_PROBS = {"uniform": 0.6, "stripes": 0.2, "noise": 0.2}
_STUDIO_STREAM = 0x5D1  # the studio draw's own generator stream, so that a room's seed gives the same room


def _log_uniform(gen: torch.Generator, low: float, high: float) -> float:
    return math.exp(math.log(low) + float(torch.rand(1, generator=gen, dtype=torch.float64)) * math.log(high / low))


def drawn_studio_spec(seed: int, config: SamplerConfig | None = None) -> SceneSpec:
    """A random :func:`studio_spec` from ``seed``: one object of one paint (uniform, stripes or
    noise of two albedos; glossy or matte), alone or with a box and a cylinder, before a black
    background, in a camera of :data:`STUDIO_FOV_DEG` that the objects fill :data:`STUDIO_FILL`
    of at :data:`STUDIO_DISTANCE_M`, lit by one lamp within :data:`STUDIO_LIGHT_CONE_DEG` of the
    camera's direction at :data:`STUDIO_LIGHT_DISTANCE` radii; the image size, exposure range and gloss ranges are
    ``config``'s. The training pool's share of such frames is ``config.studio_prob``."""
    config = config or SamplerConfig()
    gen = torch.Generator().manual_seed(int(seed) * 2 + _STUDIO_STREAM)

    def u(low: float, high: float) -> float:
        return low + (high - low) * float(torch.rand(1, generator=gen, dtype=torch.float64))

    fov = _log_uniform(gen, *STUDIO_FOV_DEG)
    others = u(0, 1) < 0.5
    distance = u(*STUDIO_DISTANCE_M)
    # The objects' width (studio_spec's layout: 6.6 radii with the box and cylinder) fills the view's
    # share (of its shorter side for the sphere alone, which the frame must not cut).
    view = 2 * distance * math.tan(math.radians(fov) / 2) * (1.0 if others else min(config.height / config.width, 1.0))
    radius = u(*STUDIO_FILL) * view / (6.6 if others else 2.0)
    # The lamp: uniform over the cap of directions within the cone about the camera's (-z).
    cos_theta = u(math.cos(math.radians(STUDIO_LIGHT_CONE_DEG)), 1.0)
    sin_theta, phi = math.sqrt(1 - cos_theta**2), u(0, 2 * math.pi)
    direction = (sin_theta * math.cos(phi), sin_theta * math.sin(phi), -cos_theta)
    names, probs = zip(*STUDIO_PATTERN_PROBS.items())
    pattern = names[int(torch.multinomial(torch.tensor(probs), 1, generator=gen))]
    level, tint = u(0.15, 0.9), [u(0.6, 1.0) for _ in range(3)]
    albedo = tuple(level * t / max(tint) for t in tint)
    second = tuple(a * u(0.3, 0.8) for a in albedo)
    glossy = u(0, 1) < config.specular_prob * 2  # objects photographed are glossier than rooms
    ks = u(*config.ks_range) if glossy else 0.0
    shininess = _log_uniform(gen, max(config.shininess_range[0], 1.0), max(config.shininess_range[1], 2.0))
    ambient = 0.0 if u(0, 1) < 0.6 else u(0.0, 0.05)
    return studio_spec(direction, width=config.width, height=config.height, fov_x_deg=fov, distance=distance,
                       radius=radius, light_distance=_log_uniform(gen, *STUDIO_LIGHT_DISTANCE), others=others,
                       albedo=albedo, ks=ks, shininess=shininess, ambient=ambient,
                       exposure=u(*config.exposure_range), seed=int(seed), pattern=pattern, second_albedo=second,
                       pattern_scale=radius * _log_uniform(gen, 0.5, 2.0))


_PANEL_STREAM = 0x9A3  # the panels' draw: its own stream, so that a room's seed gives the same room
# A ceiling panel's side (metres, drawn uniformly) and its grid of points a side: a quarter of
# 32 rooms at 128x96 as panels took 1.4 times the point-lit rooms' time to cast with 3x3 points,
# 2.3 times with 4x4 (2-core CPU, ad hoc).
PANEL_SIZE = (0.3, 0.9)
PANEL_POINTS = 3


def scene_spec(seed: int, config: SamplerConfig | None = None) -> SceneSpec:
    """The training pool's scene of ``seed``: :func:`drawn_studio_spec` with probability
    ``config.studio_prob`` (drawn from its own stream), else the room of
    :func:`selfsup.scenes.sampler.sample_scene` (the same room for the seed whatever the share);
    with probability ``config.panel_prob`` (its own stream too) that room's lights are ceiling
    panels (:func:`selfsup.scenes.camera.with_area_lights`: a square of :data:`PANEL_SIZE`
    metres a side of :data:`PANEL_POINTS` x :data:`PANEL_POINTS` points just under the room's
    top, above where the light was), their centres kept in ``meta["area_lights"]["centres"]``
    as the truth (:func:`selfsup.scenes.dataset.render_items` reports them so)."""
    config = config or SamplerConfig()
    if config.studio_prob > 0:
        pick = torch.Generator().manual_seed(int(seed) * 2 + _STUDIO_STREAM + 1)
        if float(torch.rand(1, generator=pick, dtype=torch.float64)) < config.studio_prob:
            return drawn_studio_spec(seed, config)
    spec = sample_scene(seed, config)
    if config.panel_prob > 0:
        pick = torch.Generator().manual_seed(int(seed) * 2 + _PANEL_STREAM)
        draw = torch.rand(2, generator=pick, dtype=torch.float64)
        if float(draw[0]) < config.panel_prob:
            size = PANEL_SIZE[0] + float(draw[1]) * (PANEL_SIZE[1] - PANEL_SIZE[0])
            spec, centres = with_area_lights(spec, "panel", size=size, points=PANEL_POINTS)
            spec.meta["area_lights"]["centres"] = centres.tolist()
    return spec
