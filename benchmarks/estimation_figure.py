"""The estimator's albedo-free stages on one capture frame, as one figure (docs/estimation.md).

    python -m benchmarks.estimation_figure                      # examples/capture, room_00
    python -m benchmarks.estimation_figure --frame DIR/color/ID.png --out figure.png

Six panels, each what the stage of that name computes (``selfsup.estimation``'s own
functions, the default settings): the capture's colour; the normals refitted from its
depth; the albedo segments (smooth surfaces cut by the image's edges); the albedo classes
(a surface's segments of one hue and level merged) under the search's lights; the shading
those lights explain, with the estimator's answer (crosses) and, where the folder has
``truth/``, the true lights (circles) projected into the image; the residual left (log
shading less the model and each class's level). Needs matplotlib (``pip install '.[plot]'``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_FRAME = ROOT / "examples" / "capture" / "color" / "room_00.png"
DEFAULT_OUT = ROOT / "docs" / "estimation_stages.png"


def stages(frame: Path) -> dict:
    """What each stage computes on the capture frame ``frame`` (its colour file): numpy
    images ``(H, W[, 3])`` and the lights ``(L, 2)`` in pixels (the answer's and the truth's)."""
    from benchmarks.captures import read_truth
    from render.functional import light_transport
    from selfsup.estimation import EstimateOptions, estimate_scene
    from selfsup.estimation import albedo_free
    from selfsup.estimation.prepare import prepare, within_pixels, working_range
    from selfsup.scenes.capture import linear_to_srgb, read_input

    options = EstimateOptions()
    scene = read_input(frame)
    record = estimate_scene(scene, options)
    scene, _ = working_range(within_pixels(scene, options))
    problem = prepare([scene], options)
    scale = options.tuning.albedo_free_scale
    labels = albedo_free.albedo_segments(problem)
    fit = albedo_free.search(problem, 1, labels=labels, robust_scale=scale)
    for n_lights in range(2, max(1, len(record["lights"])) + 1):
        fit = albedo_free.search(problem, n_lights, fixed=fit, labels=labels, robust_scale=scale)
    classes = albedo_free.albedo_classes(problem, labels, fit.position, fit.log_weight)
    fit, observed = albedo_free.refine_on_classes(problem, labels, fit, scale)
    g = problem.gbuffer
    weight = fit.log_weight.exp()
    diffuse = light_transport(g, observed.material, fit.position, falloff=problem.falloff, shadows="none",
                              specular=False).diffuse
    shading = weight[:, :1, None] + (weight[:, 1:, None, None] * diffuse).sum(1)  # (1, H, W)
    ratio = (observed.log_shading - shading.clamp_min(1e-12).log()).flatten(1)
    residual = torch.where(observed.pairs, ratio - observed.offsets(ratio), torch.nan).view_as(shading)
    image = problem.image[0].permute(1, 2, 0).double().numpy()
    valid = g.mask[0].numpy()
    K = g.intrinsics[0].double().numpy()

    def pixels(points) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        points = points[points[:, 2] > 0]  # lights behind the camera have no pixel
        uv = (K @ points.T).T
        return uv[:, :2] / uv[:, 2:]

    truth_file = frame.parent.parent / "truth" / f"{frame.stem}.npz"
    truth = read_truth(truth_file).light_pos.numpy() if truth_file.exists() else np.zeros((0, 3))
    return {
        "colour": linear_to_srgb(image / max(np.percentile(image[valid], 99), 1e-30)),
        "normals": np.where(valid[..., None], 0.5 - 0.5 * g.normals[0].double().numpy(), 1.0),
        "segments": labels[0].numpy(), "classes": classes[0].numpy(),
        "shading": np.where(valid, shading[0].double().numpy(), np.nan),
        "residual": residual[0].double().numpy(),
        "answer": pixels([light["position"] for light in record["lights"]]), "truth": pixels(truth),
        "id": record["id"], "found": record["light_found"],
    }


def _labels_image(labels: np.ndarray) -> np.ndarray:
    # Each label a random colour (-1: white), the same colours on every run.
    colours = np.random.default_rng(0).uniform(0.15, 0.95, size=(int(labels.max()) + 2, 3))
    colours[-1] = 1.0
    return colours[np.where(labels >= 0, labels, -1)]


def draw(panels: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(12, 6.4))
    views = [
        ("1. capture (8-bit sRGB colour)", panels["colour"], {}),
        ("2. normals refitted from the depth", panels["normals"], {}),
        (f"3. albedo segments ({int(panels['segments'].max()) + 1})", _labels_image(panels["segments"]), {}),
        (f"4. albedo classes ({int(panels['classes'].max()) + 1})", _labels_image(panels["classes"]), {}),
        ("5. shading the lights explain", panels["shading"], {"cmap": "gray"}),
        ("6. residual (log), each class's level out", panels["residual"], {"cmap": "RdBu_r", "vmin": -0.2, "vmax": 0.2}),
    ]
    for ax, (title, image, style) in zip(axes.flat, views):
        ax.imshow(image, interpolation="nearest", **style)
        ax.set_title(title, fontsize=10)
        ax.set_axis_off()
    ax = axes.flat[4]
    height, width = panels["shading"].shape
    for uv, marker, label in ((panels["truth"], "o", "truth"), (panels["answer"], "x", "estimate")):
        inside = uv[(uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)]
        if len(inside):
            ax.scatter(inside[:, 0], inside[:, 1], marker=marker, s=90, c="tab:orange" if marker == "x" else "none",
                       edgecolors="tab:cyan" if marker == "o" else None, linewidths=2, label=label)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower right", fontsize=8)
    fig.suptitle(f"{panels['id']}: the albedo-free stages of mode=estimate", fontsize=11)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frame", type=Path, default=DEFAULT_FRAME, help="a capture folder's colour file")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    if not args.frame.is_file():
        parser.error(f"--frame {args.frame}: no such colour file")
    draw(stages(args.frame), args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
