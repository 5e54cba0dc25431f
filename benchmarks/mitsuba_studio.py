"""Objects in the dark rendered by Mitsuba 3, light bouncing between their parts, and the
estimator scored on them: our analogue of the held-back DiLiGenT metal cup.

    python -m pip install "mitsuba>=3.5"      # the `mitsuba` extra; nothing else needs it
    python -m benchmarks.mitsuba_studio --shapes cup objects --materials matte gloss gold aluminium
    python -m benchmarks.mitsuba_studio --shapes cup --materials matte --integrator direct --name mitsuba_studio_direct
    python -m benchmarks.mitsuba_studio --depth integrated --name mitsuba_studio_integrated

Shapes: ``cup``, an open tube on a bottom (radius 0.2 m, 0.44 m tall, 5 m before the camera)
tilted 35 degrees towards the camera so that its inside shows, as a cup or a goblet photographed
from a little above; ``objects``, :func:`selfsup.scenes.studio.studio_spec`'s sphere, box and
cylinder. Materials (Mitsuba's BSDFs, two-sided): ``matte`` (diffuse white), ``gloss``
(``roughplastic``, GGX alpha 0.08 over a brown paint), ``gold`` and ``aluminium``
(``roughconductor``, GGX alpha 0.25 / 0.3). ``--integrator path`` (light bouncing between the
parts, 6 bounces) or ``direct`` (the lamp's light alone): the difference is what the
estimator's model, direct light and one ambient, does not hold. Each frame (one lamp, 5 m
from the object, in one of :data:`DIRECTIONS`) goes through the photo camera of the studio
(:data:`selfsup.scenes.studio.PHOTO_CAMERA`: auto exposure, sRGB, 8 bits, millimetre depth),
is estimated with ``mode=estimate``'s settings plus ``--option``s and scored by the angle
between the true direction and the object's centre to the brightest light (90 where none; a
frame the estimator refuses is a row with its reason). Results:
``benchmarks/results/<name>_<device>_<date>.*``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import write_results
from benchmarks.estimate_procedural import parse_options
from benchmarks.mitsuba_scenes import _affine, _frame, _render, lights_and_sensor, object_shapes
from selfsup.estimation.options import EstimateOptions
from selfsup.estimation.stages import estimate_scene
from selfsup.scenes.camera import camera_capture, write_capture_frame
from selfsup.scenes.capture import capture_frames, read_capture
from selfsup.scenes.integration import integrated_depth
from selfsup.scenes.sampler import SceneSpec
from selfsup.scenes.studio import DEPTHS, PHOTO_CAMERA, lamp_angle_deg, sphere_centre, studio_spec

SHAPES = ("cup", "objects")
INTEGRATORS = ("path", "direct")
MATERIALS = {
    "matte": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.78, 0.75]}},
    "gloss": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.08, "int_ior": 1.5,
              "diffuse_reflectance": {"type": "rgb", "value": [0.6, 0.25, 0.15]}},
    "gold": {"type": "roughconductor", "material": "Au", "distribution": "ggx", "alpha": 0.25},
    "aluminium": {"type": "roughconductor", "material": "Al", "distribution": "ggx", "alpha": 0.3},
}
# The lamp's directions from the object (camera frame: x right, y down, z forward): in front
# of it, from the camera's axis to 64 degrees off it, above and below, left and right.
DIRECTIONS = ((0.3, -0.5, -0.81), (-0.6, -0.3, -0.74), (0.8, -0.2, -0.56), (0.1, -0.1, -0.99),
              (-0.3, -0.7, -0.65), (0.5, 0.2, -0.84), (-0.8, 0.1, -0.59), (0.0, -0.9, -0.44))
CUP_RADIUS, CUP_HALF_HEIGHT, CUP_TILT_DEG = 0.2, 0.22, 35.0
COLUMNS = ["shape", "material", "integrator", "frame", "direction", "angle_deg", "light_found", "lights", "note"]


def _shapes(spec: SceneSpec, shape: str) -> list[dict]:
    # Mitsuba shapes of the cup, or of the spec's primitives.
    if shape != "cup":
        return [one for shapes, _ in object_shapes(spec) for one in shapes]
    centre = sphere_centre(spec).double().numpy()
    tilt = math.radians(CUP_TILT_DEG)
    axis = np.array([0.0, -math.cos(tilt), -math.sin(tilt)])  # up and towards the camera: the inside shows
    bottom = centre - CUP_HALF_HEIGHT * axis
    return [{"type": "cylinder", "p0": bottom.tolist(), "p1": (centre + CUP_HALF_HEIGHT * axis).tolist(),
             "radius": CUP_RADIUS},  # Mitsuba's cylinder is an open tube
            {"type": "disk", "to_world": _affine(_frame(-axis) @ np.diag([CUP_RADIUS] * 3), bottom)}]


def scene_dict(spec: SceneSpec, shape: str, material: str, integrator: str) -> dict:
    """Mitsuba's scene of ``shape`` in ``material`` under ``spec``'s lamp and camera (sampler seed 0)."""
    scene: dict = {"type": "scene"}
    for i, s in enumerate(_shapes(spec, shape)):
        scene[f"s{i}"] = {**s, "bsdf": {"type": "twosided", "material": MATERIALS[material]}}
    scene.update(lights_and_sensor(spec, 0))
    scene["integrator"] = {"type": "path", "max_depth": 6} if integrator == "path" else {"type": "direct"}
    return scene


def render(spec: SceneSpec, shape: str, material: str, integrator: str, spp: int, depth: str = "rendered"
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """The linear image ``(H, W, 3)`` and the depth ``(H, W)`` (metres; 0 off the object) of a frame:
    ``rendered``, or ``integrated`` from the true normals as the DiLiGenT objects' depth was made
    (:func:`selfsup.scenes.integration.integrated_depth`: the rim's hidden jump spread as a tilt)."""
    scene = scene_dict(spec, shape, material, integrator)
    aov = {"type": "aov", "aovs": "pos:position,nn:sh_normal"}
    geometry = _render({**scene, "integrator": aov}, 1, {"type": "stratified", "sample_count": 1, "jitter": False})
    points, normals = geometry[..., 0:3], geometry[..., 3:6]
    seen = np.linalg.norm(normals, axis=-1) > 0.5
    z = torch.tensor(np.where(seen, points[..., 2], 0.0), dtype=torch.float32)
    if depth == "integrated":  # two-sided surfaces: each normal turned to face the camera
        facing = np.where((np.sum(normals * points, -1) > 0)[..., None], -normals, normals)
        z = integrated_depth(torch.tensor(facing), z, spec.K.double()).float()
    return torch.tensor(_render(scene, spp), dtype=torch.float32), z


def run(shapes, materials, integrator: str, spp: int, options: EstimateOptions, name: str, write: bool = True,
        depth: str = "rendered") -> list[dict]:
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    rows = []
    for shape in shapes:
        for material in materials:
            angles = []
            for k, direction in enumerate(DIRECTIONS):
                spec = studio_spec(direction, others=shape == "objects")
                image, z = render(spec, shape, material, integrator, spp, depth)
                row = {"shape": shape, "material": material, "integrator": integrator, "frame": k,
                       "direction": list(direction), "light_found": False, "lights": 0, "note": ""}
                with tempfile.TemporaryDirectory() as folder:
                    write_capture_frame(Path(folder), "frame", camera_capture(image, z, spec.K.double(),
                                                                              PHOTO_CAMERA, seed=k))
                    try:
                        record = estimate_scene(read_capture(capture_frames(Path(folder))[0]), options)
                    except ValueError as error:  # a frame the estimator refuses: its reason, no light
                        record, row["note"] = None, str(error)[:120]
                row["angle_deg"] = 90.0 if record is None else round(lamp_angle_deg(record, spec, direction), 2)
                if record is not None:
                    row["light_found"], row["lights"] = record["light_found"], len(record["lights"])
                angles.append(row["angle_deg"])
                rows.append(row)
                print(row, flush=True)
            rows.append({"shape": shape, "material": material, "integrator": integrator, "frame": "**median**",
                         "angle_deg": round(statistics.median(angles), 2),
                         "light_found": sum(r["light_found"] for r in rows[-len(angles):]),
                         "lights": f"one light: {sum(r['lights'] == 1 for r in rows[-len(angles):])}"})
    if write:
        header = (f"Objects in the dark rendered by Mitsuba 3 (`python -m benchmarks.mitsuba_studio`, integrator "
                  f"{integrator}, {spp} samples a pixel, the depth {depth}), through the studio's photo camera, each estimated with the "
                  f"settings changed: {options.changed_settings() or 'none'}; the angle between the true lamp direction "
                  "and the object's centre to the brightest light (90 where none). Median rows: light_found = frames "
                  "with a light, lights = frames with one light.")
        print(write_results(name, torch.device("cpu"), rows, header, COLUMNS))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shapes", nargs="+", choices=SHAPES, default=list(SHAPES))
    parser.add_argument("--materials", nargs="+", choices=sorted(MATERIALS), default=list(MATERIALS))
    parser.add_argument("--integrator", choices=INTEGRATORS, default="path")
    parser.add_argument("--spp", type=int, default=256, help="samples a pixel (path tracing's noise falls with it)")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="an estimate setting or tuned constant, e.g. method=cnn (repeatable)")
    parser.add_argument("--depth", choices=DEPTHS, default="rendered",
                        help="integrated: the depth integrated from the true normals, as DiLiGenT's objects' was made")
    parser.add_argument("--name", default="mitsuba_studio")
    args = parser.parse_args()
    if args.spp < 1:
        raise SystemExit("--spp must be >= 1")
    run(args.shapes, args.materials, args.integrator, args.spp, EstimateOptions.from_settings(**parse_options(args.option)),
        args.name, depth=args.depth)


if __name__ == "__main__":
    main()
