"""Shadow methods against exact ray casting on an analytic scene, and on procedural rooms.

Sphere and box on a floor with a back wall, lights spread around the scene
(camera side, above, behind the objects, low at the side, behind the camera).
For each light and method: the share of valid pixels, away from a one-pixel
band at exact shadow edges, whose lit/shadowed class (visibility > 0.5) agrees
with exact shadow rays; the share of exactly lit pixels whose rendered value is
within 1e-4 relative; and the time of one forward pass. Results go to
benchmarks/results/shadow_accuracy_<device>_<date>.{md,json}.

    python benchmarks/shadow_accuracy.py [--height 120 --width 160]

With ``--rooms N``: the first N scenes of the procedural two-light test set
(``benchmarks.estimate_procedural``, seed ``--seed``), every light, each method's
shadows of the scene's exact depth map against the generator's exact shadow rays
(:func:`room_agreement`), the epipolar sweep also with each occluder thickness of
``--thickness`` (shares of the scene size); results to
``shadow_accuracy_rooms_<device>_<date>``.
"""

from __future__ import annotations

import argparse
import time

import torch

from benchmarks.common import write_results
from benchmarks.estimate_procedural import SETS
from render import GBuffer, Material, PointLights, render
from render.shadows import EpipolarShadowOptions, shadow_visibility
from selfsup.scenes.analytic import (compare_to_exact, intrinsics_for, objects_on_floor, render_exact_view,
                                     shadow_edge_band)
from selfsup.scenes.dataset import render_items
from selfsup.scenes.degrade import Degradations
from selfsup.scenes.sampler import SamplerConfig

LIGHTS = {
    "camera side, right": [0.6, -1.0, 0.5],
    "camera side, left": [-0.8, -0.9, 1.2],
    "above, front": [0.2, -1.5, 2.0],
    "above, front left": [-1.0, -1.5, 3.0],
    "above the objects": [0.2, -2.0, 4.3],
    "behind the objects": [0.0, -2.0, 5.5],
    "low, right": [1.5, -0.5, 2.0],
    "low, left side": [-2.5, 0.0, 4.0],
    "behind the camera": [2.0, -1.0, -1.0],
}


def run(height: int = 120, width: int = 160, methods=("epipolar", "paper"), write: bool = True):
    K = intrinsics_for(height, width)
    prims = objects_on_floor()
    rows = []
    for name, light in LIGHTS.items():
        lp = torch.tensor([light], dtype=torch.float64)
        view = render_exact_view(prims, K, height, width, lp, torch.full((1, 3), 10.0), ks=0.3)
        g = GBuffer(points=view.points[None], normals=view.normals[None], mask=view.mask[None], intrinsics=K[None])
        mat = Material(kd=torch.full((1, height, width, 3), 0.6, dtype=torch.float64),
                       ks=torch.full((1, height, width, 1), 0.3, dtype=torch.float64), shininess=20.0)
        lights = PointLights(position=lp[None], intensity=torch.full((1, 1, 3), 10.0, dtype=torch.float64))
        exact = view.visibility[..., 0]
        row = {"light": name, "position": light, "shadowed_share": round((exact[view.mask] < 0.5).double().mean().item(), 3)}
        for method in methods:
            t0 = time.perf_counter()
            out = render(g, mat, lights, torch.full((1, 3), 0.05, dtype=torch.float64), shadows=method)
            row[f"{method}_seconds"] = round(time.perf_counter() - t0, 4)
            score = compare_to_exact(view, out.visibility[0, 0], out.image[0].permute(1, 2, 0))
            row[f"{method}_agree"] = round(score.agree, 4)
            row[f"{method}_lit_within_1e-4"] = round(score.lit_within_1e4, 4)
        rows.append(row)
    mean = {"light": "**mean**"}
    for key in rows[0]:
        if key.endswith(("_agree", "_within_1e-4", "_seconds")):
            mean[key] = round(sum(r[key] for r in rows) / len(rows), 4)
    rows.append(mean)
    path = None
    if write:
        columns = ["light", "position", "shadowed_share"] + [f"{m}_{k}" for m in methods for k in ("agree", "lit_within_1e-4", "seconds")]
        header = (f"{width}x{height}, float64, exact G-buffer; agree = lit/shadowed class matches exact shadow rays "
                  f"on valid pixels away from a 1-pixel band at exact shadow edges (attached shadows included).")
        path = write_results("shadow_accuracy", torch.device("cpu"), rows, header, columns)
    return rows, path


def room_agreement(scene, exact_visibility: torch.Tensor, methods=("epipolar", "paper"),
                   thicknesses: tuple[float, ...] = ()) -> dict:
    """Each method's cast shadows of one procedural ``scene`` (its exact depth, normals
    and intrinsics) against the generator's exact shadow rays, ``exact_visibility
    (H, W, L)``, summed over its lights: :func:`setting_agreement` of each method with its
    defaults, the unbounded epipolar solid beside the default (the bounded one) when
    ``epipolar`` is among them, and the epipolar sweep with each ``scene_thickness`` of
    ``thicknesses``, named ``epipolar_T<thickness>``."""
    runs = {method: (method, None) for method in methods}
    if "epipolar" in methods:
        runs["epipolar_unbounded"] = ("epipolar", EpipolarShadowOptions(scene_thickness=None))
    runs.update({f"epipolar_T{t}": ("epipolar", EpipolarShadowOptions(scene_thickness=t)) for t in thicknesses})
    return setting_agreement(scene, exact_visibility, runs)


def setting_agreement(scene, exact_visibility: torch.Tensor, runs: dict[str, tuple[str, object]]) -> dict:
    """Pixel counts of each shadow setting ``runs`` (name -> (method, options); ``none``:
    everything lit) against exact shadow rays ``exact_visibility (H, W, L)`` of one
    procedural ``scene``. Counted on the pixels that face each light (where the shading
    is not zero anyway, so a shadow changes the image) away from a one-pixel band at
    exact shadow edges: ``pixels`` (those counted), ``shadowed`` (of them, exactly
    shadowed), and per setting ``<name>_missed`` (exactly shadowed, lit by the setting)
    and ``<name>_extra`` (exactly lit, shadowed by it)."""
    g = GBuffer.from_depth(scene.depth[None], scene.K[None], None if scene.normals is None else scene.normals[None])
    light = scene.light_pos[None].to(g.points.dtype)
    exact = exact_visibility.permute(2, 0, 1) > 0.5  # (L, H, W)
    band = shadow_edge_band(exact.to(g.points.dtype))
    toward = light[0, :, None, None] - g.points  # (L, H, W, 3)
    facing = (g.normals * toward).sum(-1) > 0
    keep = g.mask & facing & ~band
    counts = {"pixels": int(keep.sum()), "shadowed": int((keep & ~exact).sum())}
    for name, (method, options) in runs.items():
        visibility = shadow_visibility(method, g.points, g.mask, g.intrinsics, light, options)
        lit = torch.ones_like(exact) if visibility is None else visibility[0] > 0.5
        counts[f"{name}_missed"] = int((keep & ~exact & lit).sum())
        counts[f"{name}_extra"] = int((keep & exact & ~lit).sum())
    return counts


def procedural_rooms(count: int, seed: int) -> list:
    """The first ``count`` rooms of the procedural two-light test set, exactly rendered:
    each with its ``.scene`` and exact shadow rays' ``.visibility``."""
    if count < 1:
        raise ValueError(f"--rooms needs at least 1 room, got {count}")
    degradations, lights = SETS["true reflectance, 2 lights"]
    sampler = SamplerConfig(height=120, width=160, n_lights_probs=tuple(lights))
    return [exact for exact, _ in render_items([seed * 1_000_003 + i for i in range(count)], sampler,
                                               Degradations(**degradations), 2)]


def run_rooms(count: int = 32, seed: int = 9100, methods=("epipolar", "paper"), write: bool = True,
              thicknesses: tuple[float, ...] = ()):
    """:func:`room_agreement` over the first ``count`` scenes of the procedural two-light
    set: one row per scene and a total (shares of the exactly shadowed pixels)."""
    rows, total = [], {}
    for index, exact in enumerate(procedural_rooms(count, seed)):
        counts = room_agreement(exact.scene, exact.visibility, methods, thicknesses)
        names = [key.removesuffix("_missed") for key in counts if key.endswith("_missed")]  # as room_agreement names them
        for key, value in counts.items():
            total[key] = total.get(key, 0) + value
        rows.append({"scene": index, **shares(counts, names)})
    rows.append({"scene": "**all**", **shares(total, names)})
    path = None
    if write:
        columns = ["scene", "shadowed_share"] + [f"{m}_{k}" for m in names for k in ("agree", "missed", "extra")]
        header = (f"{count} procedural two-light rooms (seed {seed}, 160x120, the estimate_procedural test set), every "
                  f"light; each method's shadows of the exact depth map against the generator's exact shadow rays, on "
                  f"the pixels facing the light away from a 1-pixel band at exact shadow edges. agree: share of those "
                  f"pixels of the same lit/shadowed class; missed: exactly shadowed pixels the method lights, and "
                  f"extra: exactly lit pixels it shadows, both as shares of the exactly shadowed pixels. "
                  f"epipolar: the layer's default (a solid of 0.03 x the scene size behind each pixel, soft far end); "
                  f"epipolar_unbounded: everything behind the surface solid (the old default); epipolar_T<t>: a solid "
                  f"of t x the scene size (EpipolarShadowOptions.scene_thickness).")
        path = write_results("shadow_accuracy_rooms", torch.device("cpu"), rows, header, columns)
    return rows, path


def shares(counts: dict, methods) -> dict:
    shadowed = max(counts["shadowed"], 1)
    row = {"shadowed_share": round(counts["shadowed"] / max(counts["pixels"], 1), 3)}
    for method in methods:
        missed, extra = counts[f"{method}_missed"], counts[f"{method}_extra"]
        row[f"{method}_agree"] = round(1 - (missed + extra) / max(counts["pixels"], 1), 4)
        row[f"{method}_missed"] = round(missed / shadowed, 3)
        row[f"{method}_extra"] = round(extra / shadowed, 3)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--rooms", type=int, default=0, help="measure on this many procedural rooms instead")
    parser.add_argument("--seed", type=int, default=9100, help="seed of the procedural rooms")
    parser.add_argument("--thickness", type=float, nargs="*", default=[0.05, 0.03],
                        help="with --rooms: also the sweep with these scene thicknesses")
    args = parser.parse_args()
    rows, path = (run_rooms(args.rooms, args.seed, thicknesses=tuple(args.thickness)) if args.rooms
                  else run(args.height, args.width))
    for row in rows:
        print(row)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
