"""Forward and forward+backward time of the renderer per image.

Grid: resolutions x batch sizes x light counts x shadow methods, on the CPU and
on CUDA when present, plus the issue's target configurations. Configurations
whose work exceeds --max-work (batch * lights * pixels) are skipped and listed
as such. Results: benchmarks/results/render_speed_<device>_<date>.{md,json}.

    python benchmarks/render_speed.py                    # full grid within budget
    python benchmarks/render_speed.py --quick            # targets only

The target configurations are also measured through ``torch.compile(layer)``
(mode ``compiled``; ``compile_s`` is the time of the first forward and the first
forward+backward call, which compile): the fused elementwise kernels are what
the GPU target needs. ``--no-compile`` skips those rows.
"""

from __future__ import annotations

import argparse
import time

import torch

from benchmarks.common import device_name, machine_reference, timed, write_results
from render import GBuffer, Material, PointLights, ShadowedBlinnPhong
from selfsup.scenes.analytic import intrinsics_for, objects_on_floor, render_exact_view

# The targets, (height, width, batch, lights): 2-core CPU and one H100.
CPU_TARGET = (120, 160, 16, 1)
GPU_TARGET = (256, 256, 64, 1)

# Lights spread above and in front of the objects, cycled for several lights.
LIGHTS = [[0.2, -1.5, 2.0], [-0.8, -0.9, 1.2], [0.6, -1.0, 0.5], [-1.0, -1.5, 3.0]]


def make_inputs(height, width, batch, num_lights, device, dtype=torch.float32):
    K = intrinsics_for(height, width)
    view = render_exact_view(objects_on_floor(), K, height, width, torch.tensor([LIGHTS[0]], dtype=torch.float64),
                             torch.ones(1, 3, dtype=torch.float64))
    depth = view.depth.to(device, dtype)[None].expand(batch, height, width).contiguous()
    g = GBuffer.from_depth(depth, K.to(device, dtype))
    mat = Material(kd=torch.full((batch, height, width, 3), 0.6, device=device, dtype=dtype))
    pos = torch.tensor([LIGHTS[i % len(LIGHTS)] for i in range(num_lights)], device=device, dtype=dtype)
    pos = pos[None].expand(batch, num_lights, 3).contiguous()
    intensity = torch.full((batch, num_lights, 3), 10.0, device=device, dtype=dtype)
    ambient = torch.full((batch, 3), 0.05, device=device, dtype=dtype)
    return g, mat, pos, intensity, ambient


# Shadow settings timed beside each method's defaults on the target configurations:
# label -> (method, options). The bounded solid is what matches an independent renderer
# best (benchmarks/layer_vs_mitsuba.py).
TARGET_VARIANTS = {"epipolar, unbounded solid (the old default)": ("epipolar", {"scene_thickness": None})}


def measure(height, width, batch, num_lights, method, device, compiled: bool = False, shadow_options=None,
            label: str | None = None):
    g, mat, pos, intensity, ambient = make_inputs(height, width, batch, num_lights, device)
    layer = ShadowedBlinnPhong(shadows=method, shadow_options=shadow_options, check_finite=False)
    run_layer = torch.compile(layer) if compiled else layer

    def forward():
        with torch.no_grad():
            run_layer(g, mat, PointLights(position=pos, intensity=intensity), ambient)

    def forward_backward():
        p = pos.clone().requires_grad_(True)
        i = intensity.clone().requires_grad_(True)
        run_layer(g, mat, PointLights(position=p, intensity=i), ambient).square().mean().backward()

    compile_s = None
    if compiled:  # the first calls compile (one graph without and one with gradients)
        started = time.perf_counter()
        forward()
        forward_backward()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        compile_s = round(time.perf_counter() - started, 1)
    # The CPU's speed drifts by 20-40% between minutes: its reference, timed beside each row, lets
    # rows of different days compare by their ratio to it.
    reference = machine_reference(repeats=5)["elementwise_ns"] if device.type == "cpu" else None
    t_fwd = timed(forward, device)
    t_fb = timed(forward_backward, device)
    return {
        "device": device.type, "resolution": f"{width}x{height}", "batch": batch, "lights": num_lights,
        "shadows": label or method, "mode": "compiled" if compiled else "eager",
        "fwd_ms_per_image": round(1e3 * t_fwd / batch, 3),
        "fwd_bwd_ms_per_image": round(1e3 * t_fb / batch, 3),
        "fwd_bwd_images_per_s": round(batch / t_fb, 1), "compile_s": compile_s,
        "reference_ns": reference,
        "fwd_bwd_per_reference": None if reference is None else round(1e3 * t_fb / batch / reference, 1),
    }


def run(quick: bool = False, max_work: float | None = None, device: str | None = None, compiled: bool = True) -> list:
    """Measure the grid on ``device`` (default: CPU, and CUDA when present), and the
    target configurations compiled unless ``compiled`` is False; returns the results paths."""
    devices = [torch.device(device)] if device else [torch.device("cpu")] + (
        [torch.device("cuda")] if torch.cuda.is_available() else [])
    methods = ["epipolar", "paper", "none"]
    paths = []
    for dev in devices:
        budget = max_work or (2**22 if dev.type == "cpu" else 2**28)
        configs = [(*CPU_TARGET, m) for m in methods]
        if dev.type == "cuda":
            configs.append((*GPU_TARGET, "epipolar"))
        if not quick:
            configs += [(s, s, b, l, m) for s in (128, 256, 512) for b in (1, 16, 64) for l in (1, 2, 4) for m in methods]
        rows = []
        for h, w, b, l, m in dict.fromkeys(configs):
            if b * l * h * w > budget:
                rows.append({"device": dev.type, "resolution": f"{w}x{h}", "batch": b, "lights": l, "shadows": m,
                             "fwd_ms_per_image": "skipped (over max_work)"})
                continue
            row = measure(h, w, b, l, m, dev)
            print(row, flush=True)
            rows.append(row)
        for label, (method, options) in TARGET_VARIANTS.items():
            target = CPU_TARGET if dev.type == "cpu" else GPU_TARGET
            rows.append(measure(*target, method, dev, shadow_options=options, label=label))
            print(rows[-1], flush=True)
        if compiled:
            target = CPU_TARGET if dev.type == "cpu" else GPU_TARGET
            try:
                row = measure(*target, "epipolar", dev, compiled=True)
            except Exception as error:  # e.g. no C++ compiler for inductor's CPU kernels
                row = {"device": dev.type, "resolution": f"{target[1]}x{target[0]}", "batch": target[2],
                       "lights": target[3], "shadows": "epipolar", "mode": "compiled",
                       "fwd_ms_per_image": f"failed: {type(error).__name__}: {str(error)[:120]}"}
            print(row, flush=True)
            rows.append(row)
        header = ("Scene: sphere and box on a floor (exact depth), kd only, lights above/in front; float32; "
                  "median of >= 3 runs after a warm-up. 'epipolar' is the layer's default (a solid 0.03 of the "
                  "scene deep behind each surface, soft at both ends). Targets: CPU 160x120 batch 16, 1 light, "
                  "shadows, fwd+bwd <= 4.8 ms/image; H100 256x256 batch 64, 1 light, default shadows, >= 10,000 "
                  "images/s. mode: eager, or torch.compile(layer) (compile_s: its first two calls). On the CPU, "
                  "reference_ns: benchmarks.common.machine_reference's elementwise time, timed before the row; "
                  "fwd_bwd_per_reference: fwd+bwd ms over it, what rows of different days compare by (the CPU "
                  "target's 4.8 ms on 2026-11-26's machine, at 0.135 ns: 35.6).")
        path = write_results("render_speed", dev, rows, header,
                             ["device", "resolution", "batch", "lights", "shadows", "mode", "fwd_ms_per_image",
                              "fwd_bwd_ms_per_image", "fwd_bwd_images_per_s", "compile_s", "reference_ns",
                              "fwd_bwd_per_reference"])
        print(f"wrote {path} ({device_name(dev)})")
        paths.append(path)
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="only the target configurations")
    parser.add_argument("--max-work", type=float, default=None,
                        help="skip configs with batch*lights*pixels above this (default: 2^22 on CPU, 2^28 on CUDA)")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: both when CUDA is present)")
    parser.add_argument("--no-compile", action="store_true", help="skip the torch.compile rows")
    args = parser.parse_args()
    run(args.quick, args.max_work, args.device, not args.no_compile)


if __name__ == "__main__":
    main()
