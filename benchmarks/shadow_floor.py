"""How close to Mitsuba 3 any shadows from a depth map can be: the error floor of ``layer_vs_mitsuba``.

    python -m benchmarks.shadow_floor --scenes data/mitsuba/direct

For each open-room scene file of ``benchmarks/mitsuba_scenes.py`` (its procedural spec
drawn again from ``meta.seed``; closed rooms' added walls are not in the spec and are
left out), the layer's shading of the file's geometry, kd and true lights, with the cast
shadows' visibility:

- ``exact``: binary, a ray from each pixel's point to the light through the true
  geometry (every occluder, seen by the camera or not): the shading model's floor;
- ``depth-map march, solid T``: binary, 384 samples along that ray projected into the
  depth map, blocked where a sample lies behind the visible surface by less than ``T``
  of the scene size: the best a depth map with that solid allows;
- ``epipolar default``: the layer's own shadows.

Relative L1 on the diffuse valid pixels as ``layer_vs_mitsuba``; results
``benchmarks/results/shadow_floor_<device>_<date>.*``.
"""

from __future__ import annotations

import argparse
import math
import statistics
from pathlib import Path

import torch

from benchmarks.common import diffuse_relative_l1, write_results
from render import GBuffer, PointLights, light_transport, render
from selfsup.scenes.io import read_scene, render_inputs
from selfsup.scenes.raycast import cast_rays
from selfsup.scenes.sampler import SamplerConfig, sample_scene

COLUMNS = ["visibility", "scenes", "median_relative_l1", "mean_relative_l1"]
MARCH_SAMPLES = 384


def exact_visibility(scene, gbuffer: GBuffer) -> torch.Tensor:
    """``(1, L, H, W)`` binary visibility through the spec's true geometry."""
    H, W = scene.depth.shape
    spec = sample_scene(int(scene.meta["seed"]), SamplerConfig(height=H, width=W), n_lights=int(scene.meta["n_lights"]))
    if not torch.allclose(spec.light_position, scene.light_pos, atol=1e-4):
        raise ValueError(f"{scene.id}: its spec drawn again does not match the file (not a mitsuba_scenes.py file?)")
    mask = gbuffer.mask[0]
    points, normals = gbuffer.points[0][mask].double(), gbuffer.normals[0][mask].double()
    out = []
    for light in scene.light_pos.double():
        to_light = light - points
        distance = to_light.norm(dim=-1)
        hit = cast_rays(spec.prims.to(torch.float64), points + 1e-3 * normals, to_light / distance[:, None], t_min=1e-4)
        v = torch.ones(H, W)
        v[mask] = (hit.t >= distance - 2e-3).float()
        out.append(v)
    return torch.stack(out)[None]


def marched_visibility(gbuffer: GBuffer, light: torch.Tensor, thickness: float) -> torch.Tensor:
    """``(H, W)`` binary visibility from an exhaustive march of the depth map (see the module)."""
    K = gbuffer.intrinsics[0].double()
    H, W = gbuffer.mask.shape[1:]
    mask = gbuffer.mask[0].reshape(-1)
    points = gbuffer.points[0].double().reshape(-1, 3)
    zmap = torch.where(gbuffer.mask[0], gbuffer.points[0][..., 2].double(), math.inf)
    steps = torch.linspace(0, 1, MARCH_SAMPLES + 2, dtype=torch.float64)[1:-1]
    visibility = torch.ones(H * W, dtype=torch.float64)
    for pixels in torch.split(torch.arange(H * W)[mask], 4096):
        p = points[pixels]
        q = p[:, None] + steps[None, :, None] * (light.double() - p)[:, None]
        u = (K[0, 0] * q[..., 0] / q[..., 2] + K[0, 2]).round().long()
        v = (K[1, 1] * q[..., 1] / q[..., 2] + K[1, 2]).round().long()
        inside = (q[..., 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        z = zmap[v.clamp(0, H - 1), u.clamp(0, W - 1)]
        own = ((u - pixels[:, None] % W).abs() <= 1) & ((v - pixels[:, None] // W).abs() <= 1)
        blocked = inside & ~own & (q[..., 2] > z * (1 + 1e-3)) & (q[..., 2] < z + thickness)
        visibility[pixels] = (~blocked.any(1)).double()
    return visibility.reshape(H, W).float()


def run(folders: list[Path], thickness: float = 0.03, write: bool = True) -> tuple[list[dict], Path | None]:
    files = [p for folder in folders for p in sorted(folder.glob("*.npz"))]
    errors: dict[str, list[float]] = {}
    for path in files:
        scene = read_scene(path)
        if scene.meta.get("closed_room"):
            continue
        g, material, lights = render_inputs(scene)
        size = float((g.points[0][g.mask[0]].amax(0) - g.points[0][g.mask[0]].amin(0)).norm())
        transport = light_transport(g, material, lights.position, shadows="none", specular=False).diffuse
        kd = material.kd.permute(0, 3, 1, 2)

        def shaded(visibility: torch.Tensor) -> torch.Tensor:  # (1, L, H, W) -> (3, H, W)
            return (kd[:, :, None] * (transport * visibility)[:, None]
                    * lights.intensity.permute(0, 2, 1)[..., None, None]).sum(2)[0]

        images = {
            "exact (true geometry)": shaded(exact_visibility(scene, g)),
            f"depth-map march, solid {thickness}": shaded(torch.stack(
                [marched_visibility(g, light, thickness * size) for light in lights.position[0]])[None]),
            "epipolar default": render(g, material, PointLights(lights.position, lights.intensity), None,
                                       shadows="epipolar", falloff=scene.falloff).image[0],
        }
        for name, image in images.items():
            errors.setdefault(name, []).append(diffuse_relative_l1(image, scene, g.mask[0]))
    rows = [{"visibility": name, "scenes": len(rel), "median_relative_l1": round(statistics.median(rel), 4),
             "mean_relative_l1": round(statistics.mean(rel), 4)} for name, rel in errors.items()]
    for row in rows:
        print(row, flush=True)
    path = None
    if write:
        header = (f"Open-room scene files of Mitsuba 3's direct light ({', '.join(map(str, folders))}), the layer's "
                  "shading of their geometry, kd and true lights with each visibility (benchmarks/shadow_floor.py); "
                  "relative L1 on the diffuse valid pixels, median and mean over the scenes.")
        path = write_results("shadow_floor", torch.device("cpu"), rows, header, COLUMNS)
    return rows, path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=Path, nargs="+", required=True, help="folders of direct-light scene files")
    parser.add_argument("--thickness", type=float, default=0.03, help="the marched solid, of the scene size")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args()
    print(run(args.scenes, args.thickness, not args.no_write)[1])


if __name__ == "__main__":
    main()
