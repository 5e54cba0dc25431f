"""The alternative a user would pick: Mitsuba 3's own inverse rendering of one point light.

    python -m benchmarks.mitsuba_inverse --captures data/captures/mitsuba/direct --frames 24

For each frame (a capture or a scene file): a triangle mesh of its depth map (two
triangles per 2x2 pixels whose depths agree within ``EDGE_JUMP``; none across depth
steps), a diffuse BSDF of albedo 0.5 (a capture's assumption; the file's kd is not
used, as a user with a camera does not have it), the frame's camera, and one point
light whose position and RGB intensity Adam fits to the linear image (L2 over the valid
pixels) through ``llvm_ad_rgb`` differentiable rendering (the ``direct`` integrator's
gradient: shading, not the visibility of shadow edges), from the paper's start (above
the middle of the valid points' box), the intensity first scaled so the rendered median
matches. Reported per frame: the position and its error, and the seconds.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

EDGE_JUMP = 0.05  # relative depth difference above which a 2x2 quad is a depth step, not a surface
ALBEDO = 0.5


def _mesh(points: np.ndarray, valid: np.ndarray):
    """A Mitsuba mesh of the valid pixels' points ``(H, W, 3)`` (camera frame = world)."""
    import drjit as dr
    import mitsuba as mi

    H, W = valid.shape
    index = np.arange(H * W).reshape(H, W)
    z = points[..., 2]
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    quad_z = np.stack([z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]])
    quad_ok = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    quad_ok &= quad_z.max(0) <= (1 + EDGE_JUMP) * quad_z.min(0)
    faces = np.concatenate([np.stack([a, c, b], -1)[quad_ok], np.stack([b, c, d], -1)[quad_ok]])
    used = np.unique(faces)
    remap = np.full(H * W, -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    vertices = points.reshape(-1, 3)[used]
    mesh = mi.Mesh("depth", vertex_count=used.size, face_count=faces.shape[0], has_vertex_normals=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = dr.ravel(mi.Point3f(*vertices.T.astype(np.float32)))
    params["faces"] = dr.ravel(mi.Vector3u(*remap[faces].T.astype(np.uint32)))
    params.update()
    mesh.set_bsdf(mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": ALBEDO}}))
    return mesh


def fit_frame(image: np.ndarray, depth: np.ndarray, K: np.ndarray, iterations: int = 100, spp: int = 4,
              learning_rate: float = 0.02) -> tuple[np.ndarray, np.ndarray, float]:
    """Mitsuba 3's fit of one point light to a linear ``image (H, W, 3)`` with ``depth (H, W)``
    metres and intrinsics ``K``: ``(position (3,), intensity (3,), seconds)``; the learning
    rate is in scene sizes (the valid points' bounding-box diagonal) per step."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    started = time.perf_counter()
    H, W = depth.shape
    valid = np.isfinite(depth) & (depth > 0)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    points = np.stack([(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth], -1)
    inside = points[valid]
    lo, hi = inside.min(0), inside.max(0)
    size = float(np.linalg.norm(hi - lo))
    start = np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2])  # the paper's: above the box's middle
    fov = 2 * math.degrees(math.atan(0.5 * W / K[0, 0]))
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": fov, "fov_axis": "x",
                   "principal_point_offset_x": (K[0, 2] - (W - 1) / 2) / W,
                   "principal_point_offset_y": (K[1, 2] - (H - 1) / 2) / H,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"}},
        "depth_mesh": _mesh(points, valid),
        "light": {"type": "point", "position": start.tolist(), "intensity": {"type": "rgb", "value": 1.0}},
    })
    params = mi.traverse(scene)
    target = mi.TensorXf(np.where(valid[..., None], image, 0.0).astype(np.float32))
    weight = mi.TensorXf(np.repeat(valid[..., None], 3, -1).astype(np.float32) / max(int(valid.sum()) * 3, 1))
    first = np.array(mi.render(scene, params, spp=spp))
    scale = float(np.median(image[valid])) / max(float(np.median(first[valid])), 1e-12)
    params["light.intensity.value"] = mi.Color3f(scale, scale, scale)
    params.update()
    optimiser = mi.ad.Adam(lr=learning_rate)
    optimiser["position"] = mi.Point3f(*(float(x) for x in start / size))  # in scene sizes: one rate for any scale
    optimiser["log_intensity"] = mi.Color3f(*([math.log(max(scale, 1e-12))] * 3))
    for step in range(iterations):
        params["light.position"] = optimiser["position"] * size
        params["light.intensity.value"] = dr.exp(optimiser["log_intensity"])
        params.update()
        rendered = mi.render(scene, params, spp=spp, seed=step)
        loss = dr.sum(dr.square(rendered - target) * weight, axis=None)
        dr.backward(loss)
        optimiser.step()
    position = np.array(optimiser["position"], dtype=np.float64).reshape(-1)[:3] * size
    intensity = np.exp(np.array(optimiser["log_intensity"], dtype=np.float64).reshape(-1)[:3])
    return position, intensity, time.perf_counter() - started


def main() -> None:
    from benchmarks.captures import read_truth
    from selfsup.scenes.capture import capture_frames, read_capture

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--captures", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--iterations", type=int, default=100)
    args = parser.parse_args()
    for frame in capture_frames(args.captures)[: args.frames]:
        scene = read_capture(frame)
        truth = read_truth(args.captures / "truth" / f"{frame.color.stem}.npz")
        position, _, seconds = fit_frame(scene.image.double().numpy(), scene.depth.double().numpy(),
                                         scene.K.double().numpy(), args.iterations)
        error = float(np.linalg.norm(position - truth.light_pos[0].double().numpy())) / float(truth.scene_scale)
        print(f"{frame.color.stem}: error {error:.4f} of the scene size, {seconds:.1f} s", flush=True)


if __name__ == "__main__":
    main()
