"""Forward and forward+backward time of the renderer per image.

Grid: resolutions x batch sizes x light counts x shadow methods, on the CPU and
on CUDA when present, plus the issue's target configurations. Configurations
whose work exceeds --max-work (batch * lights * pixels) are skipped and listed
as such. Results: benchmarks/results/render_speed_<device>_<date>.{md,json}.

    python benchmarks/render_speed.py                    # full grid within budget
    python benchmarks/render_speed.py --quick            # targets only
"""

from __future__ import annotations

import argparse
import torch

from benchmarks.common import device_name, timed, write_results
from render import GBuffer, Material, PointLights, ShadowedBlinnPhong
from selfsup.scenes.analytic import intrinsics_for, objects_on_floor, render_exact_view

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


def measure(height, width, batch, num_lights, method, device):
    g, mat, pos, intensity, ambient = make_inputs(height, width, batch, num_lights, device)
    layer = ShadowedBlinnPhong(shadows=method, check_finite=False)

    def forward():
        with torch.no_grad():
            layer(g, mat, PointLights(position=pos, intensity=intensity), ambient)

    def forward_backward():
        p = pos.clone().requires_grad_(True)
        i = intensity.clone().requires_grad_(True)
        layer(g, mat, PointLights(position=p, intensity=i), ambient).square().mean().backward()

    t_fwd = timed(forward, device)
    t_fb = timed(forward_backward, device)
    return {
        "device": device.type, "resolution": f"{width}x{height}", "batch": batch, "lights": num_lights,
        "shadows": method, "fwd_ms_per_image": round(1e3 * t_fwd / batch, 3),
        "fwd_bwd_ms_per_image": round(1e3 * t_fb / batch, 3),
        "fwd_bwd_images_per_s": round(batch / t_fb, 1),
    }


def run(quick: bool = False, max_work: float | None = None, device: str | None = None) -> list:
    """Measure the grid on ``device`` (default: CPU, and CUDA when present); returns the results paths."""
    devices = [torch.device(device)] if device else [torch.device("cpu")] + (
        [torch.device("cuda")] if torch.cuda.is_available() else [])
    methods = ["epipolar", "paper", "none"]
    paths = []
    for dev in devices:
        budget = max_work or (2**22 if dev.type == "cpu" else 2**28)
        configs = [(120, 160, 16, 1, m) for m in methods]  # the CPU target
        if dev.type == "cuda":
            configs.append((256, 256, 64, 1, "epipolar"))  # the H100 target
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
        header = (f"Scene: sphere and box on a floor (exact depth), kd only, lights above/in front; float32; "
                  f"median of >= 3 runs after a warm-up. Targets: CPU 160x120 batch 16, 1 light, shadows, "
                  f"fwd+bwd < 5 ms/image; H100 256x256 batch 64, 1 light, default shadows, >= 10,000 images/s.")
        path = write_results("render_speed", dev, rows, header,
                             ["device", "resolution", "batch", "lights", "shadows", "fwd_ms_per_image",
                              "fwd_bwd_ms_per_image", "fwd_bwd_images_per_s"])
        print(f"wrote {path} ({device_name(dev)})")
        paths.append(path)
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="only the target configurations")
    parser.add_argument("--max-work", type=float, default=None,
                        help="skip configs with batch*lights*pixels above this (default: 2^22 on CPU, 2^28 on CUDA)")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: both when CUDA is present)")
    args = parser.parse_args()
    run(args.quick, args.max_work, args.device)


if __name__ == "__main__":
    main()
