"""What a real camera and a real room do to a capture, for synthetic sets judged with truth.

Our renders share the estimator's assumptions: point lights, a linear sensor behind an
sRGB curve, registered depth, one exposure. Real frames break each of them. This
module makes them break in a synthetic capture too, so that a fix for real frames is
measured against the truth:

- :func:`with_area_lights`: a light becomes a grid of points over a square, a ceiling
  panel (horizontal, just under the room's top) or a window (vertical, in front of the
  back wall); the truth stays the square's centre;
- :func:`lens_falloff`: a lens's vignetting, ``(1 + a r^2)^-2`` (the estimator divides the same
  formula out: :mod:`selfsup.estimation.vignetting`);
- :class:`CameraModel` and :func:`camera_capture`: auto exposure metered on the mean
  (bright pixels clip), grey-world auto white balance, vignetting, the sRGB curve, 8 bits,
  JPEG, colour shifted against the depth by a few pixels, depth from a structured-light
  sensor (disparity steps growing with z^2, smooth bumps, holes beside edges and at
  random), and colour and depth of other sizes (640x480; a phone's 1920x1440 colour
  beside 256x192 depth).

Each step is a switch; a :class:`CameraModel` with every switch off gives the
captures benchmark's recipe (sRGB, 8 bits, millimetres) at the exposure it is given.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from selfsup.scenes.capture import linear_to_srgb
from selfsup.scenes.io import Scene
from selfsup.scenes.sampler import SceneSpec

__all__ = ["with_area_lights", "lens_falloff", "CameraModel", "CameraCapture", "camera_capture", "write_capture_frame",
           "AREA_KINDS"]

AREA_KINDS = ("panel", "window")


def _square(normal: Tensor, size: float, points: int) -> Tensor:
    # (points^2, 3) offsets over a square of side ``size`` perpendicular to ``normal``, centred on 0.
    normal = normal / normal.norm()
    helper = torch.tensor([1.0, 0.0, 0.0]) if abs(float(normal[0])) < 0.9 else torch.tensor([0.0, 0.0, 1.0])
    u = torch.linalg.cross(normal, helper.to(normal))
    u = u / u.norm()
    v = torch.linalg.cross(normal, u)
    steps = (torch.arange(points, dtype=normal.dtype) + 0.5) / points - 0.5  # cell centres in (-0.5, 0.5)
    a, b = torch.meshgrid(steps, steps, indexing="ij")
    return size * (a.reshape(-1, 1) * u + b.reshape(-1, 1) * v)


def with_area_lights(spec: SceneSpec, kind: str, size: float = 0.6, points: int = 4,
                     wall_gap: float = 0.15) -> tuple[SceneSpec, Tensor]:
    """``spec`` with each light made an area light of ``points x points`` point lights
    (the light's intensity shared among them) over a square of side ``size`` metres, and
    the lights' centres ``(L, 3)`` (the truth to score against).

    ``kind``: ``panel`` (horizontal, its centre moved up to 0.05 m under the room's top
    along the floor's normal: a ceiling fitting, out of view above most cameras) or
    ``window`` (vertical, facing into the room, its centre moved to ``wall_gap`` in front
    of the back wall: a large soft source).
    """
    if kind not in AREA_KINDS:
        raise ValueError(f"kind must be one of {AREA_KINDS}, got {kind!r}")
    if size <= 0 or points < 1:
        raise ValueError(f"an area light needs size > 0 and points >= 1, got {size}, {points}")
    planes = spec.prims.planes  # (P, 6): a point and the normal, camera frame; the floor first, the back wall second
    floor_point, up = planes[0, :3], planes[0, 3:6] / planes[0, 3:6].norm()
    centres = []
    for light in spec.light_position:
        if kind == "panel":
            top = float(spec.meta["room_size_m"][2]) - 0.05
            centre = light + (top - float((light - floor_point) @ up)) * up
        else:
            wall_point, facing = planes[1, :3], planes[1, 3:6] / planes[1, 3:6].norm()  # the back wall faces the camera
            centre = light - (float((light - wall_point) @ facing) - wall_gap) * facing
        centres.append(centre)
    centres = torch.stack(centres)  # (L, 3)
    offsets = _square(up if kind == "panel" else planes[1, 3:6], size, points)  # (N, 3)
    position = (centres[:, None] + offsets[None]).reshape(-1, 3)  # (L, 3) + (N, 3) -> (L * N, 3)
    intensity = (spec.light_relative_intensity[:, None] / offsets.shape[0]).expand(-1, offsets.shape[0], -1).reshape(-1, 3)
    meta = {**spec.meta, "area_lights": {"kind": kind, "size_m": size, "points": points}}
    return replace(spec, light_position=position.contiguous(), light_relative_intensity=intensity.contiguous(),
                   meta=meta), centres


def lens_falloff(intrinsics: Tensor, height: int, width: int, corner_share: Tensor) -> Tensor:
    """The radial factor ``(B, H, W)`` in ``(0, 1]`` of a lens whose corners lose
    ``corner_share (B,)`` of the centre's light: ``(1 + a r^2)^-2`` with ``r^2`` the squared
    distance from the principal point in focal lengths, ``a`` set by the corners.

    Args:
        intrinsics: ``(B, 3, 3)``; corner_share: ``(B,)`` in ``[0, 1)``.

    Example:
        >>> K = torch.tensor([[[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]]])
        >>> lens_falloff(K, 120, 160, torch.tensor([0.3]))[0, 0, 0]  # a corner   # doctest: +SKIP
        tensor(0.7012)
    """
    dtype, device = intrinsics.dtype, intrinsics.device
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device),
                          torch.arange(width, dtype=dtype, device=device), indexing="ij")
    fx, fy = intrinsics[:, 0, 0, None, None], intrinsics[:, 1, 1, None, None]
    cx, cy = intrinsics[:, 0, 2, None, None], intrinsics[:, 1, 2, None, None]
    r2 = ((u - cx) / fx) ** 2 + ((v - cy) / fy) ** 2  # (B, H, W)
    corner = (width / 2 / fx) ** 2 + (height / 2 / fy) ** 2  # (B, 1, 1)
    share = corner_share.to(dtype).clamp(0.0, 0.99)[:, None, None]
    a = ((1 - share) ** -0.5 - 1) / corner  # (1 + a corner)^-2 = 1 - share
    return (1 + a * r2) ** -2


@dataclass(frozen=True)
class CameraModel:
    """A camera's processing of the linear image and its depth sensor.

    ``key``: auto exposure puts the mean of the valid linear values at a value drawn in
    this range (mean metering: bright pixels clip, as in most phones and webcams); None:
    the exposure given to :func:`camera_capture`. ``white_balance``: grey-world gains
    (each channel's mean made the others'). ``vignetting``: the corners' light falls to
    ``1 - vignetting`` of the centre's (a ``cos^4``-like radial falloff). ``jpeg_quality``:
    None for PNG. ``misregistration_px``: the colour shifted against the depth by up to
    this many (colour) pixels in each axis (two cameras a few pixels apart).
    ``disparity_step``: depth quantised as a structured-light sensor's disparity, steps of
    ``disparity_step * z^2`` metres; ``depth_bumps``: smooth bumps of this std ``* z^2``
    (a sensor's low-frequency error); ``edge_holes``: pixels beside a depth jump of more
    than this share lose their depth (the projector's shadow), ``random_holes``: a share
    of pixels lose theirs. ``color_size`` / ``depth_size``: ``(width, height)`` written
    (None: the render's); the depth's intrinsics are written.
    """

    key: tuple[float, float] | None = (0.12, 0.3)
    white_balance: bool = True
    vignetting: float = 0.3
    jpeg_quality: int | None = 85
    misregistration_px: float = 2.0
    disparity_step: float = 0.0028
    depth_bumps: float = 0.002
    edge_holes: float = 0.04
    random_holes: float = 0.01
    color_size: tuple[int, int] | None = None
    depth_size: tuple[int, int] | None = None

    def __post_init__(self):
        if self.key is not None and not (0 < self.key[0] <= self.key[1] < 1):
            raise ValueError(f"key must be None or 0 < low <= high < 1, got {self.key}")
        if not 0 <= self.vignetting < 1:
            raise ValueError(f"vignetting must be in [0, 1), got {self.vignetting}")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be None or in 1 .. 100, got {self.jpeg_quality}")
        for name in ("misregistration_px", "disparity_step", "depth_bumps", "edge_holes", "random_holes"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


@dataclass
class CameraCapture:
    """What :func:`camera_capture` writes: ``color`` ``(h, w, 3)`` uint8 sRGB (and
    ``encoded``, the file's bytes: PNG or JPEG), ``depth_mm`` ``(H', W')`` uint16 (0: none),
    ``K`` ``(3, 3)`` of the depth grid, and what the camera did (``exposure``, ``gains``
    (3,), the colour's ``shift_px``)."""

    color: np.ndarray
    encoded: bytes
    suffix: str
    depth_mm: np.ndarray
    K: np.ndarray
    exposure: float
    gains: np.ndarray
    shift_px: tuple[int, int]


def _resize_linear(image: np.ndarray, width: int, height: int) -> np.ndarray:
    # Bilinear resampling of a linear image (h, w, C) to (height, width, C) over the same field of view.
    tensor = torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)))[None].double()
    out = torch.nn.functional.interpolate(tensor, size=(height, width), mode="bilinear", align_corners=False,
                                          antialias=height < image.shape[0])
    return out[0].numpy().transpose(1, 2, 0)


def _smooth_noise(shape: tuple[int, int], rng: np.random.Generator, cells: int = 6) -> np.ndarray:
    # Unit-std noise (H, W) smooth over about a ``cells``-th of the image: a coarse grid upsampled.
    coarse = rng.standard_normal((cells + 1, cells + 1, 1))
    return _resize_linear(coarse, shape[1], shape[0])[..., 0] / 0.6


def camera_capture(image: Tensor, depth: Tensor, K: Tensor, model: CameraModel, seed: int,
                   exposure: float | None = None) -> CameraCapture:
    """A capture of a rendered frame through ``model``, reproducible from ``seed``.

    Args:
        image: ``(H, W, 3)`` linear render; depth: ``(H, W)`` metres (0: none); K: ``(3, 3)``.
        exposure: the exposure where ``model.key`` is None.
    """
    rng = np.random.default_rng(seed)  # drawn from by the colour, then by the depth
    z = depth.double().numpy()
    K = K.double().numpy().copy()
    valid = np.isfinite(z) & (z > 0)
    linear, exposure, gains, shift = _processed_colour(image.double().numpy().copy(), K, valid, model, rng, exposure)
    color, encoded, suffix = _encoded(linear, model)
    depth_mm, K = _sensed_depth(z, K, valid, model, rng)
    return CameraCapture(color, encoded, suffix, depth_mm, K, float(exposure), gains, shift)


def write_capture_frame(folder: Path, frame_id: str, shot: CameraCapture) -> None:
    """``shot`` as frame ``frame_id`` of the capture folder ``folder`` (``docs/scene-format.md``,
    "Capture folders"): ``color/<id>.png|.jpg`` as the camera encoded it, ``depth/<id>.png``
    (16-bit millimetres) and ``intrinsics/<id>.json`` of the depth grid."""
    for sub in ("color", "depth", "intrinsics"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    (folder / "color" / f"{frame_id}{shot.suffix}").write_bytes(shot.encoded)
    Image.fromarray(shot.depth_mm).save(folder / "depth" / f"{frame_id}.png")
    K = shot.K
    (folder / "intrinsics" / f"{frame_id}.json").write_text(json.dumps(
        {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}))


def _processed_colour(linear: np.ndarray, K: np.ndarray, valid: np.ndarray, model: CameraModel,
                      rng: np.random.Generator, exposure: float | None):
    # The lens's falloff, white balance, exposure, the colour's shift against the depth and
    # its grid: (linear (h, w, 3), exposure, gains (3,), shift (dx, dy)).
    H, W = valid.shape
    if model.vignetting > 0:  # a falloff in the lens, before the sensor
        lens = lens_falloff(torch.from_numpy(K)[None], H, W, torch.tensor([model.vignetting], dtype=torch.float64))
        linear *= lens[0].numpy()[..., None]
    gains = np.ones(3)
    if model.white_balance:
        means = linear[valid].mean(0)
        gains = means.mean() / np.maximum(means, 1e-12)
        linear *= gains
    if model.key is not None:
        key = math.exp(rng.uniform(math.log(model.key[0]), math.log(model.key[1])))
        exposure = key / max(float(linear[valid].mean()), 1e-12)
    elif exposure is None:
        raise ValueError("exposure is needed where the camera model has no auto exposure (key None)")
    linear *= exposure
    shift = (0, 0)
    if model.misregistration_px > 0:
        limit = int(round(model.misregistration_px))
        shift = tuple(int(s) for s in rng.integers(-limit, limit + 1, size=2))
        linear = np.roll(linear, shift, axis=(1, 0))  # (dx, dy): the colour moved against the depth
    color_w, color_h = model.color_size or (W, H)
    if (color_w, color_h) != (W, H):
        linear = _resize_linear(linear, color_w, color_h)
    return linear, exposure, gains, shift


def _encoded(linear: np.ndarray, model: CameraModel) -> tuple[np.ndarray, bytes, str]:
    # sRGB, 8 bits and the file's compression: the pixels as read back, the file's bytes, its suffix.
    color = np.round(linear_to_srgb(np.clip(linear, 0, 1)) * 255).astype(np.uint8)
    buffer = io.BytesIO()
    if model.jpeg_quality is None:
        Image.fromarray(color).save(buffer, format="PNG")
        return color, buffer.getvalue(), ".png"
    Image.fromarray(color).save(buffer, format="JPEG", quality=model.jpeg_quality)
    return np.asarray(Image.open(io.BytesIO(buffer.getvalue())).convert("RGB")), buffer.getvalue(), ".jpg"


def _sensed_depth(z: np.ndarray, K: np.ndarray, valid: np.ndarray, model: CameraModel,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    # Bumps, disparity steps and holes, then the sensor's grid: millimetres (uint16) and its K.
    H, W = z.shape
    measured = z.copy()
    if model.depth_bumps > 0:
        measured = measured + model.depth_bumps * z**2 * _smooth_noise((H, W), rng)
    if model.disparity_step > 0:
        step = np.maximum(model.disparity_step * z**2, 1e-9)
        measured = np.round(measured / step) * step
    keep = valid & (measured > 0)
    if model.edge_holes > 0:
        padded = np.pad(np.where(valid, z, 0.0), 1, mode="edge")
        near = np.max([np.abs(padded[1 + dy : 1 + dy + H, 1 + dx : 1 + dx + W] - z) for dy in (-1, 0, 1)
                       for dx in (-1, 0, 1)], axis=0)
        keep &= near <= model.edge_holes * z
    if model.random_holes > 0:
        keep &= rng.random((H, W)) >= model.random_holes
    measured = np.where(keep, measured, 0.0)
    depth_w, depth_h = model.depth_size or (W, H)
    if (depth_w, depth_h) != (W, H):
        if W % depth_w or H % depth_h or W // depth_w != H // depth_h:
            raise ValueError(f"depth_size {depth_w}x{depth_h} must divide the render's {W}x{H} by one integer")
        coarse = Scene(image=torch.zeros(H, W, 3), depth=torch.from_numpy(measured).float(),
                       K=torch.from_numpy(K).float(), kd=torch.zeros(H, W, 3), meta={}).binned(W // depth_w)
        measured, K = coarse.depth.double().numpy(), coarse.K.double().numpy()
    return np.round(measured * 1000).clip(0, 65535).astype(np.uint16), K
