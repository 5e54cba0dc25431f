"""Reading and writing scene files (``docs/scene-format.md``), in one place.

Every reader of the project goes through :func:`read_scene`; every writer through
:func:`write_scene`. A bad file raises :class:`SceneFileError` naming the file and
the problem, so that a batch of files can report it and go on.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from render import GBuffer, Material, PointLights
from render.shading import Falloff

__all__ = ["Scene", "SceneFileError", "read_scene", "write_scene", "render_inputs", "scene_gbuffer"]

log = logging.getLogger(__name__)

REQUIRED = ("image", "depth", "K", "kd", "meta")


class SceneFileError(ValueError):
    """A scene file that cannot be used; ``str()`` names the file and the reason."""

    def __init__(self, path: str | Path, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path = str(path)
        self.reason = reason


@dataclass
class Scene:
    """One RGB-D view; tensors float32, shapes as in the format (H, W first, no batch).

    ``ks``, ``normals``, ``ambient``, ``light_pos``, ``light_intensity`` and
    ``scene_scale`` are None when the file does not hold them; ``shininess`` is
    ``()`` or ``(H, W)``.
    """

    image: Tensor
    depth: Tensor
    K: Tensor
    kd: Tensor
    meta: dict
    ks: Tensor | None = None
    shininess: Tensor = field(default_factory=lambda: torch.tensor(1.0))
    normals: Tensor | None = None
    ambient: Tensor | None = None
    light_pos: Tensor | None = None
    light_intensity: Tensor | None = None
    scene_scale: Tensor | None = None

    @property
    def id(self) -> str:
        return str(self.meta.get("id", ""))

    def to(self, device: torch.device | str, copy: bool = False) -> "Scene":
        """The same scene with every tensor on ``device`` (copied even there when ``copy``)."""
        return replace(self, **{f.name: getattr(self, f.name).to(device, copy=copy) for f in fields(self)
                                if isinstance(getattr(self, f.name), Tensor)})

    @property
    def falloff(self) -> str:
        return str(self.meta.get("falloff", "inverse_square"))

    @property
    def depth_valid(self) -> Tensor:
        """``(H, W)`` the pixels with a depth (the format: 0 or non-finite is missing)."""
        return torch.isfinite(self.depth) & (self.depth > 0)

    def subsampled(self, stride: int) -> "Scene":
        """Every ``stride``-th pixel of every row and column from the first, ``K`` made
        to match (its first two rows over ``stride``): each kept pixel keeps its depth,
        so its 3D point is the one it had; the lights and the truth are unchanged."""
        if not (isinstance(stride, int) and stride >= 1):
            raise ValueError(f"stride must be an integer >= 1, got {stride!r}")
        if stride == 1:
            return self
        H, W = self.image.shape[:2]

        def pick(value: Tensor | None) -> Tensor | None:  # the per-pixel fields (H, W, ...)
            per_pixel = value is not None and value.dim() >= 2 and tuple(value.shape[:2]) == (H, W)
            return value[::stride, ::stride].contiguous() if per_pixel else value

        K = self.K.clone()
        K[:2] /= stride
        return replace(self, image=pick(self.image), depth=pick(self.depth), kd=pick(self.kd), ks=pick(self.ks),
                       shininess=pick(self.shininess), normals=pick(self.normals), K=K)

    def cropped(self, top: int, left: int, height: int, width: int) -> "Scene":
        """The ``height x width`` pixels from row ``top`` and column ``left``, ``K``'s centre
        moved to match: each kept pixel keeps its depth and its 3D point; the lights and the
        truth are unchanged."""
        H, W = self.image.shape[:2]
        if not (0 <= top and 0 <= left and height >= 1 and width >= 1 and top + height <= H and left + width <= W):
            raise ValueError(f"a crop of {width}x{height} at ({left}, {top}) does not lie inside the {W}x{H} image")

        def pick(value: Tensor | None) -> Tensor | None:  # the per-pixel fields (H, W, ...)
            per_pixel = value is not None and value.dim() >= 2 and tuple(value.shape[:2]) == (H, W)
            return value[top : top + height, left : left + width].contiguous() if per_pixel else value

        K = self.K.clone()
        K[0, 2] -= left
        K[1, 2] -= top
        return replace(self, image=pick(self.image), depth=pick(self.depth), kd=pick(self.kd), ks=pick(self.ks),
                       shininess=pick(self.shininess), normals=pick(self.normals), K=K)

    def binned(self, factor: int) -> "Scene":
        """The scene on a grid ``factor`` times coarser, each pixel one ``factor x factor``
        block (rows and columns past the last whole block dropped): the image, kd and ks
        averaged over the block's pixels with a depth (linear light: what a sensor of
        larger pixels would see, with less noise and JPEG error than one pixel of it), the
        depth the median of those (a block across an edge takes one side, never a point
        between), normals averaged and renormalised, ``K`` moved to the blocks' centres; a
        block with fewer than half the depths of the frame's typical block has none (half
        the block on a dense depth; half of what a lattice of holes leaves, where the depth
        was registered from a coarser sensor's grid). The lights and the truth are unchanged.

        Example:
            >>> scene.binned(4).image.shape  # a 640x480 scene   # doctest: +SKIP
            torch.Size([120, 160, 3])
        """
        if not (isinstance(factor, int) and factor >= 1):
            raise ValueError(f"factor must be an integer >= 1, got {factor!r}")
        if factor == 1:
            return self
        H, W = self.image.shape[:2]
        h, w = H // factor, W // factor
        if h == 0 or w == 0:
            raise ValueError(f"a {W}x{H} image has no whole {factor}x{factor} block")
        valid = self.depth_valid[: h * factor, : w * factor]
        # (H, W) -> (h, w, factor * factor): each block's pixels on the last axis.
        blocks = lambda x: x[: h * factor, : w * factor].reshape(h, factor, w, factor, *x.shape[2:]).transpose(1, 2) \
            .reshape(h, w, factor * factor, *x.shape[2:])  # noqa: E731
        inside = blocks(valid)  # (h, w, f*f)
        count = inside.sum(-1)  # (h, w)
        # A block keeps a depth where it holds at least half the valid pixels of the frame's typical
        # block that has any: half the block where the depth is dense; where it was registered from a
        # coarser sensor's grid (a lattice of holes in every block: the shelf bin's RealSense frames,
        # a third of the pixels), half of what the lattice leaves.
        typical = float(count[count > 0].float().median()) if bool((count > 0).any()) else factor * factor
        kept = count * 2 >= min(factor * factor, typical)

        def mean(value: Tensor | None) -> Tensor | None:  # the per-pixel fields (H, W, ...) over the block's valid pixels
            if value is None or value.dim() < 2 or tuple(value.shape[:2]) != (H, W):
                return value
            b = blocks(value)
            weight = inside.reshape(*inside.shape, *[1] * (b.dim() - 3)).to(b.dtype)
            # A block without valid pixels: the plain mean (its depth is missing anyway).
            return torch.where(weight.sum(2) > 0, (b * weight).sum(2) / weight.sum(2).clamp_min(1), b.mean(2))

        # The median of the valid depths: invalid ones sorted to the end as +inf.
        depth_blocks = blocks(self.depth)
        depths = torch.where(inside, depth_blocks, torch.full_like(depth_blocks, math.inf)).sort(-1).values
        middle = ((count - 1).clamp_min(0) // 2)[..., None]
        depth = torch.where(kept, depths.gather(-1, middle)[..., 0], torch.zeros(()))
        normals = mean(self.normals)
        if normals is not None:
            normals = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # 0 where none was given stays 0
        K = self.K.clone()
        # Block (i, j) covers pixels i*f .. i*f + f - 1: its centre, i*f + (f - 1) / 2, becomes i.
        K[:2, 2] = (K[:2, 2] - (factor - 1) / 2) / factor
        K[:2, :2] /= factor
        return replace(self, image=mean(self.image), depth=depth, kd=mean(self.kd), ks=mean(self.ks),
                       shininess=mean(self.shininess), normals=normals, K=K)


def _shape_ok(array: np.ndarray, *shapes: tuple) -> bool:
    return any(array.shape == s for s in shapes)


def read_scene(path: str | Path) -> Scene:
    """Read and validate a scene file.

    Raises:
        SceneFileError: unreadable file, missing key, wrong shape, non-finite or
            negative image, non-finite intrinsics, or no pixel with valid depth.
    """
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
        arrays = {k: data[k] for k in data.files}
    except Exception as error:  # numpy raises many kinds for a corrupt file
        raise SceneFileError(path, f"cannot read as .npz ({type(error).__name__}: {error})") from None
    missing = [k for k in REQUIRED if k not in arrays]
    if missing:
        raise SceneFileError(path, f"missing key(s) {', '.join(missing)}")
    image, depth = arrays["image"], arrays["depth"]
    # Integers are a capture's raw units, not the format's: 8-bit images are gamma-encoded
    # sRGB (the model is linear in light), 16-bit depth a sensor's millimetres (the lights
    # would come out in millimetres, not metres). Read as numbers they are silently wrong.
    hints = {"image": " (8-bit images are usually gamma-encoded sRGB: decode to linear RGB floats)",
             "depth": " (16-bit depth is usually a sensor's millimetres: divide to metres as floats)",
             "kd": " (8-bit albedo: divide by 255, decoded to linear)"}
    for key in ("image", "depth", "kd", "ks", "normals", "ambient"):
        kind = arrays[key].dtype.kind if key in arrays else "f"
        if kind != "f":
            raise SceneFileError(path, f"{key} must be floating point, got {arrays[key].dtype}"
                                       + (hints.get(key, "") if kind in "iu" else ""))
    for key in ("K", "shininess", "scene_scale", "light_pos", "light_intensity"):  # exact in integers too
        if key in arrays and arrays[key].dtype.kind not in "fiu":
            raise SceneFileError(path, f"{key} must be numbers, got {arrays[key].dtype}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise SceneFileError(path, f"image must have shape (H, W, 3), got {image.shape}")
    H, W = image.shape[:2]
    expected = {
        "depth": [(H, W)], "K": [(3, 3)], "kd": [(H, W, 3)], "ks": [(H, W, 3), (H, W, 1)],
        "shininess": [(), (H, W)], "normals": [(H, W, 3)], "ambient": [(3,)],
        "scene_scale": [()],
    }
    for key, shapes in expected.items():
        if key in arrays and not _shape_ok(arrays[key], *shapes):
            raise SceneFileError(path, f"{key} must have shape {' or '.join(map(str, shapes))}, got {arrays[key].shape}")
    for key in ("light_pos", "light_intensity"):
        if key in arrays and (arrays[key].ndim != 2 or arrays[key].shape[1] != 3):
            raise SceneFileError(path, f"{key} must have shape (n, 3), got {arrays[key].shape}")
    if ("light_pos" in arrays) != ("light_intensity" in arrays) or (
        "light_pos" in arrays and arrays["light_pos"].shape != arrays["light_intensity"].shape
    ):
        raise SceneFileError(path, "light_pos and light_intensity must both be present with the same shape")
    for key in ("image", "K", "kd", "ks", "shininess", "ambient", "light_pos", "light_intensity"):
        if key in arrays and not np.isfinite(arrays[key]).all():
            raise SceneFileError(path, f"{key} holds non-finite values")
    K = arrays["K"]
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1], atol=1e-6) and K[1, 0] == 0):
        raise SceneFileError(path, f"K must be pinhole intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
                                   f"got {K.tolist()}")
    if K[0, 1] != 0:
        raise SceneFileError(path, f"K has skew K[0, 1] = {K[0, 1]}: intrinsics with skew are not supported")
    if (image < 0).any():
        raise SceneFileError(path, "image holds negative values (it must be linear RGB >= 0)")
    for key in ("kd", "ks", "ambient"):
        if key in arrays and (arrays[key] < 0).any():
            raise SceneFileError(path, f"{key} holds negative values (reflectance and light are >= 0)")
    if "shininess" in arrays and (arrays["shininess"] <= 0).any():
        raise SceneFileError(path, "shininess must be > 0")
    kd_max = float(arrays["kd"].max())
    if kd_max > 1.5:  # percent or 8-bit values stored as floats, most likely
        log.warning("%s: kd reaches %.3g, but the format's albedo is in [0, 1]: the lights' intensities come out "
                    "divided by the same factor (positions are unaffected)", path, kd_max)
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        raise SceneFileError(path, "no pixel has a valid depth (empty valid mask)")
    median_depth = float(np.median(depth[valid]))
    if median_depth > 100:  # a sensor's millimetres as floats, most likely
        log.warning("%s: the median depth is %.4g, but the format's depth is in metres: the lights come out in the "
                    "depth's units", path, median_depth)
    try:
        meta = json.loads(str(arrays["meta"]))
    except json.JSONDecodeError as error:
        raise SceneFileError(path, f"meta is not JSON ({error})") from None
    if not isinstance(meta, dict):
        raise SceneFileError(path, "meta must be a JSON object")
    falloffs = [f.value for f in Falloff]
    if meta.get("falloff", Falloff.INVERSE_SQUARE.value) not in falloffs:
        raise SceneFileError(path, f"meta.falloff must be one of {falloffs}, got {meta['falloff']!r}")
    meta.setdefault("id", path.stem)

    def tensor(key):
        # np.array, not np.ascontiguousarray: that one returns a 0-d array as shape (1,),
        # which made a scalar shininess a per-pixel-less (1,) no Material accepts.
        return torch.from_numpy(np.array(arrays[key], dtype=np.float32, order="C")) if key in arrays else None

    return Scene(
        image=tensor("image"), depth=tensor("depth"), K=tensor("K"), kd=tensor("kd"), meta=meta,
        ks=tensor("ks"), shininess=tensor("shininess") if "shininess" in arrays else torch.tensor(1.0),
        normals=tensor("normals"), ambient=tensor("ambient"), light_pos=tensor("light_pos"),
        light_intensity=tensor("light_intensity"), scene_scale=tensor("scene_scale"),
    )


def write_scene(path: str | Path, scene: Scene) -> None:
    """Write ``scene`` as an ``.npz`` file that :func:`read_scene` (or ``numpy.load``) reads."""
    arrays = {"meta": np.array(json.dumps(scene.meta))}
    for key in ("image", "depth", "K", "kd", "ks", "shininess", "normals", "ambient", "light_pos",
                "light_intensity", "scene_scale"):
        value = getattr(scene, key)
        if value is not None:
            arrays[key] = value.detach().cpu().numpy().astype(np.float32)
    np.savez_compressed(path, **arrays)


def scene_gbuffer(depth: Tensor, K: Tensor, normals: Tensor | None, ids: list[str]) -> GBuffer:
    """The G-buffer of scene files' ``depth (B, H, W)``, ``K (B, 3, 3)`` and ``normals
    (B, H, W, 3)`` (None: none given) as the format reads them: a missing normal (all
    zero) is estimated from the depth there (``GBuffer.from_depth``'s
    ``missing_normals="from_depth"``), and normals that face away from the camera on
    most valid pixels of an image (the other sign convention; the format's face it)
    are turned round, with a warning naming the file (``ids``, one per image). The
    devset's and the Mitsuba files' own normals face away on at most 0.02% of pixels,
    where sensor noise tilts them past the view ray."""
    gbuffer = GBuffer.from_depth(depth, K, normals, missing_normals="from_depth")
    if normals is None:  # all estimated from the depth: they face the camera
        return gbuffer
    facing = (gbuffer.normals * -gbuffer.points).sum(-1) > 0
    away = (~facing & gbuffer.mask).flatten(1).sum(1) > 0.5 * gbuffer.mask.flatten(1).sum(1)
    if not bool(away.any()):
        return gbuffer
    for scene_id, turned in zip(ids, away.tolist()):
        if turned:
            log.warning("%s: the normals face away from the camera on most pixels (the format's face it): "
                        "turned round", scene_id)
    turn = away[:, None, None] & ~facing  # not those estimated from the depth, which face it already
    return replace(gbuffer, normals=torch.where(turn[..., None], -gbuffer.normals, gbuffer.normals))


def render_inputs(scene: Scene) -> tuple[GBuffer, Material, PointLights | None]:
    """Batch-of-one renderer inputs of a scene: G-buffer (:func:`scene_gbuffer`), material
    and (if known) its lights."""
    gbuffer = scene_gbuffer(scene.depth[None], scene.K[None], None if scene.normals is None else scene.normals[None],
                            [scene.id])
    shininess = scene.shininess if scene.shininess.dim() == 0 else scene.shininess[None]
    material = Material(kd=scene.kd[None], ks=None if scene.ks is None else scene.ks[None], shininess=shininess)
    lights = None
    if scene.light_pos is not None:
        lights = PointLights(position=scene.light_pos[None], intensity=scene.light_intensity[None])
    return gbuffer, material, lights
