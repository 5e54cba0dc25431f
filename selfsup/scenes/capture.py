"""Camera captures in: colour and depth images of an RGB-D camera, read as scenes.

The capture-folder layout (``docs/scene-format.md``, "Capture folders"; other tools write it)::

    DIR/color/<id>.png|.jpg        colour, 8- or 16-bit sRGB (decoded to linear RGB here)
    DIR/depth/<id>.png             16-bit depth, metres = value / depth_scale (default 1000: millimetres); 0 or 65535 = missing
                                   (.npy / .tif float depth in metres accepted too)
    DIR/intrinsics.json            {"fx", "fy", "cx", "cy"} (pixels, OpenCV camera) for every frame, or {"K": 3x3}
    DIR/intrinsics/<id>.json       the same for one frame; takes precedence

A frame is a colour file and a depth file of the same stem; its scene's id is that
stem. Other files and folders are ignored. A capture knows no albedo, materials,
normals or ambient: the scene gets ``kd`` 0.5 everywhere (the estimator fits such a
scene albedo-free, and its intensities are those that light an albedo of 0.5 to the
image's values), normals from the depth and an unknown ambient.

Colour and depth of different sizes (a phone's 1920x1440 colour beside 256x192 depth):
where the aspects agree the colour is area-averaged in linear light onto the depth's
grid, and the intrinsics are those of the depth image.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from selfsup.scenes.io import Scene, SceneFileError, read_scene

__all__ = ["CaptureFrame", "capture_frames", "is_capture_folder", "read_capture", "capture_normals", "capture_geometry",
           "read_input", "frame_of_color", "color_and_depth_frame", "srgb_to_linear", "linear_to_srgb", "COLOR_SUFFIXES",
           "DEPTH_SUFFIXES", "ASSUMED_ALBEDO"]

COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".png", ".npy", ".tif", ".tiff")
ASSUMED_ALBEDO = 0.5  # a capture's kd: the intensities are those lighting this albedo to the image's values
ASPECT_TOLERANCE = 0.01  # relative difference of the aspects of colour and depth still taken as one


@dataclass(frozen=True)
class CaptureFrame:
    """One frame of a capture: its files and how to read them (picklable: it travels to
    worker processes). ``intrinsics``: ``(fx, fy, cx, cy)`` overriding the files, or None.
    ``str(frame)`` is its colour file, the name errors and summaries use. ``prefix``: put
    before its id (a folder of capture folders: ``<sub-folder>/``, ids unique across them)."""

    color: Path
    depth: Path | None
    intrinsics_file: Path | None
    depth_scale: float = 1000.0
    intrinsics: tuple[float, float, float, float] | None = None
    prefix: str = ""
    name: str | None = None  # the id's own part where the colour file's stem is not it (7-Scenes' "<id>.color.png")
    video_frame: int | None = None  # the colour is this frame of the video ``color`` (a phone app's rgb.mp4)
    confidence: Path | None = None  # a depth confidence image (0, 1, 2): depth below ``min_confidence`` is missing
    min_confidence: int = 1
    normals: Path | None = None  # ``normals/<id>.npy``: the surfaces' unit normals on the depth's grid, where known

    @property
    def id(self) -> str:
        return self.prefix + (self.name or self.color.stem)

    def __str__(self) -> str:
        return str(self.color)

    def read(self) -> Scene:
        return read_capture(self)


def is_capture_folder(path: str | Path) -> bool:
    """Whether ``path`` is a directory in the capture layout (``color/`` beside ``depth/``)."""
    path = Path(path)
    return path.is_dir() and (path / "color").is_dir() and (path / "depth").is_dir()


def _by_stem(folder: Path, suffixes: tuple[str, ...]) -> dict[str, Path]:
    if not folder.is_dir():
        return {}
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)
    out: dict[str, Path] = {}
    for p in files:  # one file a stem: the first suffix in the list's order wins
        if p.stem not in out or suffixes.index(p.suffix.lower()) < suffixes.index(out[p.stem].suffix.lower()):
            out[p.stem] = p
    return out


def _intrinsics_file(stem: str, roots: list[Path]) -> Path | None:
    # The first of <root>/intrinsics/<stem>.json (the frame's own) and <root>/intrinsics.json
    # (every frame's) that exists, root by root.
    candidates = [path for root in roots for path in (root / "intrinsics" / f"{stem}.json", root / "intrinsics.json")]
    return next((path for path in candidates if path.is_file()), None)


def _normals_file(stem: str, roots: list[Path]) -> Path | None:
    # The first <root>/normals/<stem>.npy that exists, root by root (a frame's normal map is optional).
    return next((path for path in (root / "normals" / f"{stem}.npy" for root in roots) if path.is_file()), None)


def _override(intrinsics) -> tuple[float, float, float, float] | None:
    return None if intrinsics is None else tuple(float(x) for x in intrinsics)


def capture_frames(folder: str | Path, depth_scale: float = 1000.0,
                   intrinsics: tuple[float, float, float, float] | None = None, prefix: str = "") -> list[CaptureFrame]:
    """The frames of a capture folder, in the order of their stems (``prefix``: before each id).

    A colour file without a depth file of its stem is a frame too, with ``depth`` None:
    reading it fails with a message naming the missing file, so that the other frames
    are still estimated. Depth files without colour are ignored.
    """
    folder = Path(folder)
    _check_depth_scale(depth_scale)
    colors = _by_stem(folder / "color", COLOR_SUFFIXES)
    depths = _by_stem(folder / "depth", DEPTH_SUFFIXES)
    normals = _by_stem(folder / "normals", (".npy",))
    return [CaptureFrame(colors[stem], depths.get(stem), _intrinsics_file(stem, [folder]), float(depth_scale),
                         _override(intrinsics), prefix, normals=normals.get(stem)) for stem in sorted(colors)]


def _check_depth_scale(depth_scale: float) -> None:
    if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"estimate.depth_scale must be a number > 0 (depth units per metre: 1000 for millimetres), "
                         f"got {depth_scale!r}")


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """The sRGB transfer function undone: ``encoded`` in [0, 1] -> linear light in [0, 1]."""
    encoded = np.clip(encoded, 0.0, 1.0)
    return np.where(encoded <= 0.04045, encoded / 12.92, ((encoded + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function: linear light in [0, 1] -> encoded in [0, 1] (clipped)."""
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)


def _read_image(path: Path) -> np.ndarray:
    # PNG and JPEG through Pillow (a 16-bit RGB PNG comes back at 8 bits of precision, at
    # the right scale; 16-bit grey keeps its 16), TIFF through tifffile (float depth).
    import imageio.v3 as iio

    try:
        return np.asarray(iio.imread(path, plugin="tifffile" if path.suffix.lower() in (".tif", ".tiff") else "pillow"))
    except Exception as error:  # imageio raises many kinds for a bad file
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else ""
        raise SceneFileError(path, f"cannot read the image ({type(error).__name__}: {first_line}); is it a valid "
                                   f"{path.suffix.lstrip('.').upper()} file?") from None


def _color_codes(path: Path, video_frame: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    # The 8- or 16-bit sRGB codes (H, W, 3) of a colour file (or of frame ``video_frame`` of a
    # video) and the table of their linear values (float64 in [0, 1], one entry a code: a
    # decoded frame costs its codes, not three float64 arrays of its size).
    if video_frame is not None:
        from selfsup.scenes.video import video_frame as read_frame

        pixels = read_frame(path, video_frame)
    else:
        pixels = _read_image(path)
    if pixels.ndim == 2:  # grey: the same value in each channel
        pixels = np.repeat(pixels[..., None], 3, axis=2)
    if pixels.ndim != 3 or pixels.shape[2] not in (3, 4):
        raise SceneFileError(path, f"colour must be an RGB image (H, W, 3), got shape {pixels.shape}")
    if pixels.dtype not in (np.uint8, np.uint16):
        raise SceneFileError(path, f"colour must be 8- or 16-bit sRGB, got {pixels.dtype}: save it as an 8- or "
                                   f"16-bit PNG or a JPEG")
    full_scale = np.iinfo(pixels.dtype).max
    return pixels[..., :3], srgb_to_linear(np.arange(full_scale + 1, dtype=np.float64) / float(full_scale))


def _depth(path: Path | None, color: Path, depth_scale: float) -> np.ndarray:
    # Depth in metres (H, W) float64, 0 where missing.
    if path is None:
        raise SceneFileError(color, f"no depth file of stem {color.stem!r} in {color.parent.parent / 'depth'} "
                                    f"(expected depth/{color.stem}.png, 16-bit millimetres, or .npy / .tif metres)")
    if path.suffix.lower() == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except Exception as error:
            raise SceneFileError(path, f"cannot read as .npy ({type(error).__name__}: {error})") from None
    else:
        raw = _read_image(path)
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[..., 0]
    if raw.ndim != 2:
        raise SceneFileError(path, f"depth must be one channel (H, W), got shape {raw.shape}")
    if raw.dtype == np.uint8:
        raise SceneFileError(path, "depth is 8-bit, which cannot hold a depth map (256 steps): save it as a 16-bit "
                                   "PNG of millimetres (estimate.depth_scale=1000) or as .npy / .tif float metres")
    if raw.dtype.kind in "iu":
        # 65535, the largest 16-bit value, marks a missing depth (7-Scenes) as 0 does: no
        # RGB-D sensor measures 65 m (millimetres) or 13 m (TUM's 5000 a metre).
        depth = np.where(raw == np.iinfo(np.uint16).max, 0, raw).astype(np.float64) / depth_scale
    elif raw.dtype.kind == "f":
        depth = raw.astype(np.float64)  # float depth is in metres
    else:
        raise SceneFileError(path, f"depth must be 16-bit integers or floats, got {raw.dtype}")
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    if not (depth > 0).any():
        raise SceneFileError(path, "depth is zero (missing) on every pixel: no geometry to light")
    return depth


def _intrinsics(frame: CaptureFrame) -> np.ndarray:
    # K (3, 3) of the frame's files, or of the override.
    if frame.intrinsics is not None:
        values = frame.intrinsics
        if len(values) != 4:
            raise ValueError(f"estimate.intrinsics must be [fx, fy, cx, cy], got {list(values)}")
        fx, fy, cx, cy = values
    else:
        path = frame.intrinsics_file
        if path is None:
            root = frame.color.parent.parent
            raise SceneFileError(frame.color, f"no intrinsics: write {root / 'intrinsics.json'} (every frame) or "
                                              f"{root / 'intrinsics' / (frame.id + '.json')} as "
                                              '{"fx": ..., "fy": ..., "cx": ..., "cy": ...} (pixels), or give '
                                              "estimate.intrinsics=[fx,fy,cx,cy]")
        form = '{"fx", "fy", "cx", "cy"} (pixels) or {"K": 3x3}'
        try:
            data = json.loads(path.read_text())
            if not isinstance(data, dict):
                raise ValueError(f"it holds a {type(data).__name__}, not an object")
            missing = [key for key in ("fx", "fy", "cx", "cy") if key not in data]
            if "K" not in data and missing:
                # Named by the intrinsics file and the keys it lacks, not by the colour file and a KeyError.
                raise SceneFileError(path, f"the intrinsics file {path} lacks {', '.join(missing)}: it must be JSON {form}")
            if "K" in data:
                K = np.asarray(data["K"], dtype=np.float64)
                if K.shape != (3, 3):
                    raise ValueError(f"K must be 3x3, got shape {K.shape}")
                fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
            else:
                fx, fy, cx, cy = (float(data[key]) for key in ("fx", "fy", "cx", "cy"))
        except SceneFileError:
            raise
        except (OSError, ValueError, TypeError) as error:
            raise SceneFileError(path, f"the intrinsics file {path} must be JSON {form} "
                                       f"({type(error).__name__}: {error})") from None
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if not (np.isfinite(K).all() and fx > 0 and fy > 0):
        raise SceneFileError(frame.intrinsics_file or frame.color, f"intrinsics need finite fx, fy > 0, got "
                                                                   f"fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    return K


# Target rows resampled at a time from a colour larger than its depth: an 8000x6000 frame
# onto 256x192 holds about 500 of its rows as floats at once, not all 6000.
RESAMPLE_ROWS = 16


def _area_weights(source: int, target: int) -> np.ndarray:
    # (target, source): the overlap of each target pixel with each source pixel, rows summing to 1.
    edges = np.arange(target + 1) * (source / target)
    lo, hi = edges[:-1, None], edges[1:, None]
    pixel = np.arange(source)[None]
    overlap = np.clip(np.minimum(hi, pixel + 1) - np.maximum(lo, pixel), 0, None)
    return overlap / overlap.sum(1, keepdims=True)


def _area_resample(codes: np.ndarray, table: np.ndarray, height: int, width: int) -> np.ndarray:
    # The linear values ``table[codes]`` of (h, w, 3) codes area-averaged onto a (height, width)
    # grid of the same extent: each target pixel the mean of the source area it covers,
    # partial source pixels weighted; RESAMPLE_ROWS target rows at a time.
    rows, cols = _area_weights(codes.shape[0], height), _area_weights(codes.shape[1], width)
    out = np.empty((height, width, 3))
    for start in range(0, height, RESAMPLE_ROWS):
        band = rows[start : start + RESAMPLE_ROWS]
        used = np.flatnonzero(band.any(0))  # the source rows this band covers, consecutive
        lo, hi = int(used[0]), int(used[-1]) + 1
        out[start : start + RESAMPLE_ROWS] = np.einsum("ih,hwc,jw->ijc", band[:, lo:hi], table[codes[lo:hi]], cols,
                                                       optimize=True)
    return out


def capture_geometry(frame: CaptureFrame) -> tuple[np.ndarray, np.ndarray]:
    """A frame's depth ``(H, W)`` float64 metres (0 where missing, or of low confidence where
    the frame has a confidence image) and ``K (3, 3)`` of the depth image: its geometry,
    without decoding its colour."""
    depth = _depth(frame.depth, frame.color, frame.depth_scale)
    if frame.confidence is not None:
        confidence = _read_image(frame.confidence)
        if confidence.shape[:2] != depth.shape:
            raise SceneFileError(frame.confidence, f"confidence {confidence.shape[1]}x{confidence.shape[0]} is not "
                                                   f"the depth's size {depth.shape[1]}x{depth.shape[0]}")
        depth = np.where(confidence.reshape(depth.shape) >= frame.min_confidence, depth, 0.0)
    return depth, _intrinsics(frame)


def read_capture(frame: CaptureFrame) -> Scene:
    """The scene of one capture frame: linear image, depth in metres, K of the depth
    image, kd :data:`ASSUMED_ALBEDO` everywhere, no ambient; the normals of
    ``normals/<id>.npy`` where the folder has them (:func:`capture_normals`), else none
    (from the depth).

    Raises:
        SceneFileError: naming the file and the fix (unreadable image, 8-bit or empty
            depth, no depth of the stem, no intrinsics, sizes whose aspects differ,
            normals of another grid or not finite).
    """
    codes, table = _color_codes(frame.color, frame.video_frame)
    depth, K = capture_geometry(frame)
    (h, w), (H, W) = codes.shape[:2], depth.shape
    if (h, w) != (H, W):
        if abs((w / h) / (W / H) - 1) > ASPECT_TOLERANCE:
            raise SceneFileError(frame.color, f"colour {w}x{h} and depth {W}x{H} differ in aspect "
                                              f"({w / h:.4f} against {W / H:.4f}): crop or register them to one "
                                              "field of view")
        image = _area_resample(codes, table, H, W)  # the intrinsics are the depth image's
    else:
        image = table[codes]
    meta = {"id": frame.id, "generator": "capture", "falloff": "inverse_square",
            "albedo": f"unknown: kd {ASSUMED_ALBEDO} assumed everywhere", "color": str(frame.color),
            "depth": str(frame.depth), "color_size": [w, h], "full_scale": float(table[-1])}

    def tensor(array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))

    normals = None if frame.normals is None else tensor(capture_normals(frame.normals, (H, W)))
    if normals is not None:
        meta["normals"] = str(frame.normals)
    return Scene(image=tensor(image), depth=tensor(depth), K=tensor(K),
                 kd=torch.full((H, W, 3), ASSUMED_ALBEDO), meta=meta, normals=normals)


def capture_normals(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """A capture's normal map ``(H, W, 3)`` float (camera frame, OpenCV axes; a photometric-stereo
    set's, a scanner's) on the depth's grid ``shape``, each nonzero vector made unit; all-zero
    vectors stay zero (missing: taken from the depth there). A depth integrated from normals
    is a tilted sheet where parts hide each other, and its normals are wrong over the whole
    object (``benchmarks/results/integrated_depth_cpu2_2026-12-07.md``): the normals themselves
    are what to give."""
    try:
        normals = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise SceneFileError(path, f"not a readable .npy normal map ({error})") from None
    if normals.shape != (*shape, 3) or not np.issubdtype(normals.dtype, np.floating):
        raise SceneFileError(path, f"normals must be a float array {shape[1]}x{shape[0]}x3 on the depth's grid "
                                   f"(H, W, 3), got {normals.dtype} {normals.shape}")
    if not np.isfinite(normals).all():
        raise SceneFileError(path, "normals hold NaN or inf: write all-zero vectors where a normal is missing")
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    return np.where(length > 0, normals / np.maximum(length, 1e-30), 0.0)


def color_and_depth_frame(color: str | Path, depth: str | Path, depth_scale: float = 1000.0,
                          intrinsics: tuple[float, float, float, float] | None = None) -> CaptureFrame:
    """The frame of a single colour file and its depth file (``estimate.depth``);
    intrinsics from ``intrinsics``, else ``intrinsics/<stem>.json`` or ``intrinsics.json``
    beside the colour file's folder or in it; normals from ``normals/<stem>.npy`` there, if any."""
    color, depth = Path(color), Path(depth)
    _check_depth_scale(depth_scale)
    roots = [color.parent.parent, color.parent]
    return CaptureFrame(color, depth if depth.exists() else None, _intrinsics_file(color.stem, roots),
                        float(depth_scale), _override(intrinsics), normals=_normals_file(color.stem, roots))


def frame_of_color(color: str | Path, depth_scale: float = 1000.0) -> CaptureFrame:
    """The frame of a colour file inside a capture folder (``DIR/color/<id>.png``): its
    depth and intrinsics found by the layout (a missing depth fails on reading, named)."""
    color = Path(color)
    root = color.parent.parent
    if not (color.is_file() and color.parent.name == "color" and is_capture_folder(root)):
        raise SceneFileError(color, f"not a colour image of a capture folder ({root}/color/ beside {root}/depth/)")
    _check_depth_scale(depth_scale)
    # The depth file of the stem by its names alone: a list of a million frames of one
    # folder costs a few lookups a frame, not a listing of the folder each.
    depth = next((path for path in (root / "depth" / f"{color.stem}{suffix}" for suffix in DEPTH_SUFFIXES)
                  if path.is_file()), None)
    if depth is None:  # upper-case suffixes: the folder's listing
        depth = _by_stem(root / "depth", DEPTH_SUFFIXES).get(color.stem)
    return CaptureFrame(color, depth, _intrinsics_file(color.stem, [root]), float(depth_scale),
                        normals=_normals_file(color.stem, [root]))


def read_input(item: str | Path | CaptureFrame) -> Scene:
    """What ``mode=estimate`` or ``mode=insert`` is given, as a scene: a capture frame, a
    colour image of a capture folder (:func:`frame_of_color`), or a scene file."""
    if isinstance(item, CaptureFrame):
        return read_capture(item)
    path = Path(item)
    if path.suffix.lower() in COLOR_SUFFIXES:
        return read_capture(frame_of_color(path))
    return read_scene(path)
