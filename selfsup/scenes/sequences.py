"""Frame sequences with exact ground truth, for the tracker (``mode=track``).

One scene of :func:`selfsup.scenes.sampler.sample_scene`, then per frame a change of
its lights or of the camera, every frame rendered by the exact ray caster
(:func:`selfsup.scenes.exact.render_specs`) and written as a scene file with its
frame's true lights. The kinds (:data:`SEQUENCE_KINDS`):

- ``static``: nothing moves (the frames differ by their image noise only: the tracker's jitter);
- ``moving_light``: one light along a horizontal half circle;
- ``moving_camera``: one still light, the camera orbiting a point ahead of it (up to
  ``CAMERA_SWING_DEG`` either way), so every light moves in the camera's frame;
- ``switch``: two still lights, the second switched on a third of the way through and
  off at two thirds;
- ``two_lights``: two lights, the first moving as in ``moving_light``, the second still.

Albedo textures are drawn in camera coordinates: under ``moving_camera`` they slide a
little on the surfaces; the geometry, the shadows and the lights are exact.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import torch
from torch import Tensor

from selfsup.scenes.degrade import Degradations, degrade
from selfsup.scenes.exact import render_specs
from selfsup.scenes.io import Scene, write_scene
from selfsup.scenes.raycast import Primitives
from selfsup.scenes.sampler import SamplerConfig, SceneSpec, sample_scene, signed_distance

__all__ = ["SEQUENCE_KINDS", "sequence_specs", "render_sequence", "write_sequence", "CAMERA_SWING_DEG",
           "render_orbit", "orbit_pose", "orbited", "light_behind_camera"]

SEQUENCE_KINDS = ("static", "moving_light", "moving_camera", "switch", "two_lights")
CAMERA_SWING_DEG = 8.0  # the moving camera's orbit, either side of the first frame's view
PATH_RADIUS = 0.12  # a moving light's half circle: this share of the room's smaller floor side
_TRIES = 50  # seeds tried for a scene whose light path stays clear of every surface


def _up(spec: SceneSpec) -> Tensor:
    return spec.prims.planes[0, 3:6].double()  # the floor's normal, in the camera frame


def _light_path(spec: SceneSpec, light: int, frames: int, margin: float) -> Tensor | None:
    """``(frames, 3)`` positions of ``light`` along a horizontal half circle from where it is,
    or None when no such path (of either turn) keeps ``margin`` from every surface."""
    start = spec.light_position[light].double()
    up = _up(spec)
    across = torch.linalg.cross(up, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    across = across / across.norm()
    along = torch.linalg.cross(across, up)
    radius = PATH_RADIUS * min(spec.meta["room_size_m"][0], spec.meta["room_size_m"][1])
    turn = torch.linspace(0.0, math.pi, frames, dtype=torch.float64)[:, None]
    prims = _double(spec.prims)
    for sign in (1.0, -1.0):
        centre = start - sign * radius * across
        path = centre + sign * radius * (torch.cos(turn) * across + torch.sin(turn) * along)
        if bool((signed_distance(prims, path) > margin).all()):
            return path.float()
    return None


def _double(prims: Primitives) -> Primitives:
    return Primitives(*(getattr(prims, f.name).double() for f in dataclasses.fields(prims)))


def _orbit(spec: SceneSpec, angle_deg: float) -> tuple[Tensor, Tensor]:
    # The rotation R (3, 3) and pivot (3,) of the camera turned ``angle_deg`` about the vertical
    # through a point ahead (at the depth of the room's middle): a point x of the first
    # camera's frame is R (x - pivot) + pivot in the turned camera's.
    up = _up(spec)
    pivot = torch.tensor([0.0, 0.0, 0.5 * spec.meta["room_size_m"][1]], dtype=torch.float64)
    a = math.radians(-angle_deg)
    k = torch.tensor([[0, -up[2], up[1]], [up[2], 0, -up[0]], [-up[1], up[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(a) * k + (1 - math.cos(a)) * (k @ k), pivot  # Rodrigues


def orbit_pose(spec: SceneSpec, angle_deg: float) -> Tensor:
    """The camera-to-world ``(4, 4)`` float64 of the camera turned ``angle_deg`` as
    ``moving_camera`` and ``orbit`` turn it, the world being the unturned camera's frame."""
    R, pivot = _orbit(spec, angle_deg)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = R.T
    pose[:3, 3] = pivot - R.T @ pivot
    return pose


def orbited(spec: SceneSpec, angle_deg: float) -> SceneSpec:
    """``spec`` seen by its camera turned ``angle_deg`` about the vertical through a point
    ahead (at the depth of the room's middle): everything turns the other way in the camera's frame."""
    R, pivot = _orbit(spec, angle_deg)

    def point(x: Tensor) -> Tensor:
        return ((x.double() - pivot) @ R.T + pivot).float()

    def direction(x: Tensor) -> Tensor:
        return (x.double() @ R.T).float()

    p = spec.prims
    boxes = torch.cat([point(p.boxes[:, :3]), p.boxes[:, 3:6],
                       (R.float()[None] @ p.boxes[:, 6:15].reshape(-1, 3, 3)).reshape(-1, 9)], 1)
    prims = Primitives(planes=torch.cat([point(p.planes[:, :3]), direction(p.planes[:, 3:6])], 1),
                       spheres=torch.cat([point(p.spheres[:, :3]), p.spheres[:, 3:4]], 1), boxes=boxes,
                       cylinders=torch.cat([point(p.cylinders[:, :3]), direction(p.cylinders[:, 3:6]),
                                            p.cylinders[:, 6:8]], 1))
    return dataclasses.replace(spec, prims=prims, light_position=point(spec.light_position))


def _frames_of(kind: str, spec: SceneSpec, frames: int, margin: float) -> list[SceneSpec] | None:
    # The frames' specs of one drawn scene, or None when a light's path would touch a surface.
    if kind == "static":
        return [spec] * frames
    if kind == "moving_camera":
        swing = torch.linspace(-CAMERA_SWING_DEG, CAMERA_SWING_DEG, frames).tolist()
        return [orbited(spec, angle) for angle in swing]
    if kind == "switch":
        first, last = frames // 3, 2 * frames // 3
        one = dataclasses.replace(spec, light_position=spec.light_position[:1],
                                  light_relative_intensity=spec.light_relative_intensity[:1])
        return [spec if first <= f < last else one for f in range(frames)]
    path = _light_path(spec, 0, frames, margin)
    if path is None:
        return None
    moved = []
    for f in range(frames):
        position = spec.light_position.clone()
        position[0] = path[f]
        moved.append(dataclasses.replace(spec, light_position=position))
    return moved


def sequence_specs(kind: str, seed: int, frames: int = 24, config: SamplerConfig | None = None) -> list[SceneSpec]:
    """The specs of ``frames`` frames of a sequence of ``kind`` (:data:`SEQUENCE_KINDS`)
    from the first scene at or after ``seed`` whose moving light stays clear of every surface."""
    if kind not in SEQUENCE_KINDS:
        raise ValueError(f"unknown sequence kind {kind!r}; available: {', '.join(SEQUENCE_KINDS)}")
    if not (isinstance(frames, int) and frames >= 2):
        raise ValueError(f"a sequence needs at least 2 frames, got {frames!r}")
    config = config or SamplerConfig(height=120, width=160)
    lights = 2 if kind in ("switch", "two_lights") else 1
    for attempt in range(_TRIES):
        spec = sample_scene(seed + attempt, config, n_lights=lights)
        specs = _frames_of(kind, spec, frames, config.light_margin)  # metres, as the spec's
        if specs is not None:
            return [dataclasses.replace(s, meta={**s.meta, "sequence": kind, "frame": f}) for f, s in enumerate(specs)]
    raise ValueError(f"no scene of seeds {seed} .. {seed + _TRIES - 1} keeps a {kind} light clear of the surfaces")


def render_sequence(kind: str, seed: int, frames: int = 24, config: SamplerConfig | None = None,
                    degradations: Degradations | None = None, samples: int = 2) -> list[Scene]:
    """The frames of :func:`sequence_specs` as scene files' contents (truth lights of each
    frame, ids ``<kind>_<seed>_<frame>``); ``degradations`` drawn afresh for every frame."""
    specs = sequence_specs(kind, seed, frames, config)
    degradations = degradations or Degradations()
    scenes = []
    for f, rendered in enumerate(render_specs(specs, samples=samples)):
        scene = degrade(rendered.scene, degradations, seed * 1000 + f)
        scene.meta.update(id=f"{kind}_{seed}_{f:03d}", sequence=kind, frame=f)
        scenes.append(scene)
    return scenes


# Where :func:`light_behind_camera` hangs a light: this share of the room's depth behind
# the camera and of its height above it (the rooms are open towards the camera and have no
# ceiling, so nothing stands between such a light and the surfaces the camera sees).
BEHIND_DEPTH = 0.25
BEHIND_HEIGHT = 0.3


def light_behind_camera(spec: SceneSpec, light: int = 0, margin: float = 0.3) -> SceneSpec | None:
    """``spec`` with light ``light`` moved behind its camera and above it (along the floor,
    :data:`BEHIND_DEPTH` of the room's depth back, :data:`BEHIND_HEIGHT` of its height up),
    its power scaled to light the camera's surroundings as before (by the squared distance
    to the camera); None when that place is within ``margin`` (metres) of a surface. Out
    of view in every frame of :func:`render_orbit`'s turns, its light on every surface."""
    up = _up(spec)
    forward = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    forward = forward - (forward @ up) * up  # the camera's view along the floor
    _, depth, height = spec.meta["room_size_m"]
    position = -BEHIND_DEPTH * depth * forward / forward.norm() + BEHIND_HEIGHT * height * up
    if not bool(signed_distance(_double(spec.prims), position[None]) > margin):
        return None
    lights, power = spec.light_position.clone(), spec.light_relative_intensity.clone()
    old = lights[light].double().norm()
    lights[light] = position.float()
    power[light] = (power[light].double() * (position.norm() / old) ** 2).float()
    return dataclasses.replace(spec, light_position=lights, light_relative_intensity=power)


def render_orbit(seed: int, frames: int = 12, swing_deg: float = 30.0, config: SamplerConfig | None = None,
                 n_lights: int = 1, degradations: Degradations | None = None, samples: int = 2,
                 spec: SceneSpec | None = None) -> tuple[list[Scene], list[Tensor], Tensor]:
    """A posed scan of one still room: its camera turned from ``-swing_deg`` to ``swing_deg``
    about the vertical through the room's middle (as ``moving_camera``, wider), ``frames``
    frames. Returns the frames (ids ``orbit_<seed>_<frame>``, each with its camera-frame
    truth), their camera-to-world poses ``(4, 4)`` and the lights in the world ``(L, 3)``
    (the unturned camera's frame). ``spec``: the room (drawn from ``seed`` when None)."""
    if not (isinstance(frames, int) and frames >= 1):
        raise ValueError(f"a scan needs at least 1 frame, got {frames!r}")
    config = config or SamplerConfig(height=120, width=160)
    spec = spec if spec is not None else sample_scene(seed, config, n_lights=n_lights)
    angles = torch.linspace(-swing_deg, swing_deg, frames).tolist() if frames > 1 else [0.0]
    degradations = degradations or Degradations()
    scenes = []
    for f, rendered in enumerate(render_specs([orbited(spec, a) for a in angles], samples=samples)):
        scene = degrade(rendered.scene, degradations, seed * 1000 + f, visibility=rendered.visibility)
        scene.meta.update(id=f"orbit_{seed}_{f:03d}", sequence="orbit", frame=f, angle_deg=angles[f])
        scenes.append(scene)
    return scenes, [orbit_pose(spec, a) for a in angles], spec.light_position.double()


def write_sequence(scenes: list[Scene], folder: str | Path) -> list[Path]:
    """``folder/frame_<NNN>.npz`` for each scene, in order."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for f, scene in enumerate(scenes):
        path = folder / f"frame_{f:03d}.npz"
        write_scene(path, scene)
        paths.append(path)
    return paths
