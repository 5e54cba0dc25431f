"""Posed RGB-D sequences in: capture frames with their camera-to-world poses.

Layouts read as they are (``docs/scan.md``):

- a capture folder (``color/``, ``depth/``, intrinsics) with ``poses.json``
  (``{"<id>": 4x4 camera-to-world}``) or ``poses.txt`` (one frame a line, TUM's order:
  ``<id> tx ty tz qx qy qz qw``, the first field the frame's id);
- a TUM RGB-D sequence (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``; depth 5000 a
  metre): each colour image takes the depth image and the ground-truth pose nearest in
  time (within :data:`TUM_MAX_DT` seconds; the others are left out); intrinsics from
  ``intrinsics.json`` beside them, else the TUM's default (Freiburg 1: 517.3, 516.5, 318.6, 255.3);
- a 7-Scenes sequence (``frame-NNNNNN.color.png|jpg``, ``frame-NNNNNN.depth.png`` in mm with
  65535 missing, ``frame-NNNNNN.pose.txt`` a 4x4 camera-to-world); intrinsics from
  ``intrinsics.json``, else 7-Scenes' (585, 585, 320, 240);
- a Stray Scanner export (``rgb.mp4``, ``depth/NNNNNN.png`` in mm at 256x192,
  ``confidence/NNNNNN.png``, ``camera_matrix.csv`` the video's intrinsics, ``odometry.csv``
  ``timestamp, frame, x, y, z, qx, qy, qz, qw`` with ARKit's camera axes, turned to OpenCV's):
  the video's frames averaged onto the depth's grid, its intrinsics scaled to it, depth of
  low confidence left out; reading the video needs the ``video`` extra (PyAV).

Poses are camera-to-world with OpenCV camera axes (x right, y down, z forward), in metres.
Each is checked: finite, a rotation (orthonormal within :data:`ROTATION_TOLERANCE`, determinant
+1: a determinant of -1 is a mirrored, left-handed convention), last row ``0 0 0 1``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from selfsup.scenes.capture import COLOR_SUFFIXES, CaptureFrame, capture_frames, is_capture_folder

__all__ = ["PosedFrame", "posed_frames", "check_pose", "quaternion_pose", "ROTATION_TOLERANCE", "TUM_MAX_DT",
           "PoseError", "ARKIT_TO_OPENCV", "depth_agreement", "check_convention", "CONVENTIONS"]

ROTATION_TOLERANCE = 1e-3  # |R^T R - I| and |det R - 1| beyond this: not a rotation
TUM_MAX_DT = 0.02  # seconds between a colour image and the depth image or pose it takes (TUM's associate.py)
TUM_DEFAULT_INTRINSICS = (517.3, 516.5, 318.6, 255.3)  # Freiburg 1, the TUM benchmark's colour camera
SEVEN_SCENES_INTRINSICS = (585.0, 585.0, 320.0, 240.0)


class PoseError(ValueError):
    """A pose that cannot be a camera-to-world rigid transform, or frames without poses."""


@dataclass(frozen=True)
class PosedFrame:
    """A capture frame and its pose ``(4, 4)`` float64 camera-to-world (OpenCV axes, metres)."""

    frame: CaptureFrame
    pose: np.ndarray

    @property
    def id(self) -> str:
        return self.frame.id

    def __str__(self) -> str:
        return str(self.frame)


def check_pose(pose, name: str) -> np.ndarray:
    """``pose`` as a checked ``(4, 4)`` float64 camera-to-world matrix; ``name`` says whose.

    Raises:
        PoseError: naming the frame and how the pose fails (shape, non-finite, not a rotation,
            a mirror, a last row other than 0 0 0 1).
    """
    matrix = np.asarray(pose, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise PoseError(f"{name}: a pose must be a 4x4 camera-to-world matrix, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise PoseError(f"{name}: the pose holds non-finite values")
    if not np.allclose(matrix[3], [0, 0, 0, 1], atol=1e-6):
        raise PoseError(f"{name}: the pose's last row is {matrix[3].tolist()}, not [0, 0, 0, 1]: a rigid transform's is")
    rotation = matrix[:3, :3]
    error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if error > ROTATION_TOLERANCE:
        raise PoseError(f"{name}: the pose's 3x3 part is not a rotation (R^T R differs from the identity by {error:.3g}):"
                        " scaled or sheared poses are not rigid")
    if np.linalg.det(rotation) < 0:
        raise PoseError(f"{name}: the pose's rotation has determinant -1, a mirror: a left-handed convention (flip one "
                        "axis to get OpenCV's x right, y down, z forward)")
    return matrix


def quaternion_pose(tx: float, ty: float, tz: float, qx: float, qy: float, qz: float, qw: float,
                    name: str) -> np.ndarray:
    """The 4x4 camera-to-world of a position and a unit quaternion (TUM's ``tx ty tz qx qy qz qw``)."""
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if not math.isfinite(norm) or abs(norm - 1) > 0.01:
        raise PoseError(f"{name}: the quaternion ({qx}, {qy}, {qz}, {qw}) is not of unit length ({norm:.4g})")
    x, y, z, w = qx / norm, qy / norm, qz / norm, qw / norm
    pose = np.eye(4)
    pose[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    pose[:3, 3] = [tx, ty, tz]
    return pose


def _pose_lines(path: Path) -> dict[str, np.ndarray]:
    # ``<key> tx ty tz qx qy qz qw`` lines (``#`` comments skipped) by their first field.
    poses = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != 8:
            raise PoseError(f"{path} line {number}: expected 'id tx ty tz qx qy qz qw', got {len(fields)} fields")
        try:
            values = [float(v) for v in fields[1:]]
        except ValueError:
            raise PoseError(f"{path} line {number}: the pose's fields must be numbers") from None
        poses[fields[0]] = quaternion_pose(*values, name=f"{path} line {number}")
    return poses


def _folder_poses(folder: Path) -> dict[str, np.ndarray]:
    # A capture folder's poses.json or poses.txt by frame id.
    if (folder / "poses.json").is_file():
        try:
            data = json.loads((folder / "poses.json").read_text())
        except json.JSONDecodeError as error:
            raise PoseError(f"{folder / 'poses.json'} is not JSON ({error})") from None
        if not isinstance(data, dict):
            raise PoseError(f"{folder / 'poses.json'} must be an object {{\"<id>\": 4x4 camera-to-world}}")
        return {str(key): check_pose(value, f"{folder / 'poses.json'} [{key!r}]") for key, value in data.items()}
    if (folder / "poses.txt").is_file():
        return _pose_lines(folder / "poses.txt")
    raise PoseError(f"{folder}: no poses.json or poses.txt beside color/ and depth/ (a scan needs each frame's "
                    "camera-to-world pose)")


def _intrinsics_override(folder: Path, default: tuple[float, float, float, float]) -> tuple | None:
    # ``intrinsics.json`` beside a sequence's files, else ``default`` (its dataset's camera).
    path = folder / "intrinsics.json"
    if not path.is_file():
        return default
    data = json.loads(path.read_text())
    return tuple(float(data[key]) for key in ("fx", "fy", "cx", "cy"))


def _timed_list(path: Path) -> list[tuple[float, str]]:
    # TUM's ``timestamp filename`` lines.
    entries = []
    for line in path.read_text().splitlines():
        fields = line.split()
        if fields and not fields[0].startswith("#"):
            entries.append((float(fields[0]), fields[1] if len(fields) > 1 else " ".join(fields[1:])))
    return entries


def _nearest(times: np.ndarray, t: float) -> int | None:
    if times.size == 0:
        return None
    i = int(np.abs(times - t).argmin())
    return i if abs(times[i] - t) <= TUM_MAX_DT else None


def _tum_frames(folder: Path) -> list[PosedFrame]:
    colours, depths = _timed_list(folder / "rgb.txt"), _timed_list(folder / "depth.txt")
    truth = []
    for line in (folder / "groundtruth.txt").read_text().splitlines():
        fields = line.split()
        if fields and not fields[0].startswith("#"):
            truth.append((float(fields[0]), [float(v) for v in fields[1:8]]))
    depth_times = np.array([t for t, _ in depths])
    pose_times = np.array([t for t, _ in truth])
    intrinsics = _intrinsics_override(folder, TUM_DEFAULT_INTRINSICS)
    frames = []
    for t, name in colours:
        d, p = _nearest(depth_times, t), _nearest(pose_times, t)
        if d is None or p is None:
            continue  # no depth or pose near it in time: not a posed frame
        color = folder / name
        frame = CaptureFrame(color, folder / depths[d][1], None, 5000.0, intrinsics)
        frames.append(PosedFrame(frame, quaternion_pose(*truth[p][1], name=f"{folder / 'groundtruth.txt'} at {t}")))
    return frames


def _seven_scenes_frames(folder: Path) -> list[PosedFrame]:
    intrinsics = _intrinsics_override(folder, SEVEN_SCENES_INTRINSICS)
    frames = []
    for color in sorted(p for p in folder.iterdir() if p.name.endswith(tuple(f".color{s}" for s in COLOR_SUFFIXES))):
        stem = color.name.split(".color")[0]
        depth, pose_file = folder / f"{stem}.depth.png", folder / f"{stem}.pose.txt"
        if not pose_file.is_file():
            raise PoseError(f"{color}: no pose file {pose_file.name} beside it")
        pose = check_pose(np.loadtxt(pose_file), str(pose_file))
        frame = CaptureFrame(color, depth if depth.is_file() else None, None, 1000.0, intrinsics, name=stem)
        frames.append(PosedFrame(frame, pose))
    return frames


# ARKit's camera axes (x right, y up, z backwards) to OpenCV's (x right, y down, z forwards).
ARKIT_TO_OPENCV = np.diag([1.0, -1.0, -1.0])
STRAY_MIN_CONFIDENCE = 1  # Stray Scanner's depth confidence (0 low, 1 medium, 2 high): low is left out


def _stray_frames(folder: Path) -> list[PosedFrame]:
    # Stray Scanner's export: rgb.mp4, depth/NNNNNN.png (mm), confidence/NNNNNN.png,
    # camera_matrix.csv (the video's intrinsics), odometry.csv (ARKit camera-to-world).
    from selfsup.scenes.video import video_size

    video = folder / "rgb.mp4"
    K = np.loadtxt(folder / "camera_matrix.csv", delimiter=",")
    if K.shape != (3, 3):
        raise PoseError(f"{folder / 'camera_matrix.csv'}: expected a 3x3 matrix, got shape {K.shape}")
    width, _ = video_size(video)
    rows = [line.split(",") for line in (folder / "odometry.csv").read_text().splitlines()[1:] if line.strip()]
    frames = []
    for number, row in enumerate(rows, 2):
        if len(row) != 9:
            raise PoseError(f"{folder / 'odometry.csv'} line {number}: expected 'timestamp, frame, x, y, z, qx, qy, "
                            f"qz, qw', got {len(row)} fields")
        index = int(float(row[1]))
        pose = quaternion_pose(*map(float, row[2:]), name=f"{folder / 'odometry.csv'} line {number}")
        pose[:3, :3] = pose[:3, :3] @ ARKIT_TO_OPENCV
        depth = folder / "depth" / f"{index:06d}.png"
        confidence = folder / "confidence" / f"{index:06d}.png"
        if not frames:  # the depth grid's intrinsics: the video's, scaled (pixel centres kept)
            import imageio.v3 as iio

            scale = iio.improps(depth).shape[1] / width
            intrinsics = (K[0, 0] * scale, K[1, 1] * scale, (K[0, 2] + 0.5) * scale - 0.5, (K[1, 2] + 0.5) * scale - 0.5)
        frame = CaptureFrame(video, depth if depth.is_file() else None, None, 1000.0, intrinsics, name=f"{index:06d}",
                             video_frame=index, confidence=confidence if confidence.is_file() else None,
                             min_confidence=STRAY_MIN_CONFIDENCE)
        frames.append(PosedFrame(frame, pose))
    return frames


# The conventions a pose file may be in by mistake, each as what turns it into ours: the
# inverse (world-to-camera given), and OpenGL's camera axes (y up, z backwards).
CONVENTIONS = {"world-to-camera (give camera-to-world: invert each pose)": "inverse",
               "OpenGL camera axes, y up and z backwards (turn them to OpenCV's: pose @ diag(1, -1, -1, 1))": "opengl"}
AGREEMENT_MARGIN = 0.25  # another convention must agree on this share of points more to be named


def _converted(pose: np.ndarray, how: str) -> np.ndarray:
    if how == "inverse":
        return np.linalg.inv(pose)
    if how == "opengl":
        return pose @ np.diag([1.0, -1.0, -1.0, 1.0])
    return pose


def depth_agreement(depth_a: np.ndarray, K_a: np.ndarray, pose_a: np.ndarray, depth_b: np.ndarray,
                    K_b: np.ndarray, pose_b: np.ndarray, stride: int = 4) -> float:
    """The share of frame a's points (every ``stride``-th valid pixel) that frame b sees where
    its own depth puts a surface (within 5% of the depth), of those that fall in b's image in
    front of its camera (0 where none does): how well two frames' depths agree under their
    poses. Depths ``(H, W)`` metres, ``K`` ``(3, 3)``, poses camera-to-world."""
    v, u = np.mgrid[0 : depth_a.shape[0] : stride, 0 : depth_a.shape[1] : stride]
    z = depth_a[::stride, ::stride]
    valid = np.isfinite(z) & (z > 0)
    z, u, v = z[valid], u[valid], v[valid]
    points = np.stack([(u - K_a[0, 2]) / K_a[0, 0] * z, (v - K_a[1, 2]) / K_a[1, 1] * z, z], 1)
    relative = np.linalg.inv(pose_b) @ pose_a
    seen = points @ relative[:3, :3].T + relative[:3, 3]
    front = seen[:, 2] > 1e-6
    x = np.round(seen[front, 0] / seen[front, 2] * K_b[0, 0] + K_b[0, 2]).astype(int)
    y = np.round(seen[front, 1] / seen[front, 2] * K_b[1, 1] + K_b[1, 2]).astype(int)
    inside = (x >= 0) & (x < depth_b.shape[1]) & (y >= 0) & (y < depth_b.shape[0])
    if not inside.any():
        return 0.0
    there = depth_b[y[inside], x[inside]]
    expected = seen[front][inside, 2]
    return float(np.mean((there > 0) & (np.abs(there - expected) <= 0.05 * expected)))


def check_convention(frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]], name: str) -> None:
    """Name a pose convention that makes the frames' depths agree much better than the
    given poses do. ``frames``: ``(depth, K, pose)`` of a few frames of one scan, in order;
    each neighbouring pair is compared (:func:`depth_agreement`) under the poses as given
    and under each of :data:`CONVENTIONS`.

    Raises:
        PoseError: another convention agrees on :data:`AGREEMENT_MARGIN` more of the points.
    """
    if len(frames) < 2:
        return

    def agreement(how: str) -> float:
        pairs = zip(frames[:-1], frames[1:])
        return float(np.mean([depth_agreement(a[0], a[1], _converted(a[2], how), b[0], b[1], _converted(b[2], how))
                              for a, b in pairs]))

    given = agreement("given")
    other, label = max((agreement(how), label) for label, how in CONVENTIONS.items())
    if other > given + AGREEMENT_MARGIN:
        raise PoseError(f"{name}: the poses look like {label}: the frames' depths agree on {other:.0%} of their "
                        f"points that way and on {given:.0%} as given (each frame's points seen from the next)")


def posed_frames(folder: str | Path, depth_scale: float = 1000.0,
                 intrinsics: tuple[float, float, float, float] | None = None) -> list[PosedFrame]:
    """The posed frames of ``folder`` in any layout of the module's doc, in order (a capture
    folder's by id, TUM's by time, 7-Scenes' by name); ``depth_scale`` and ``intrinsics`` as
    :func:`selfsup.scenes.capture.capture_frames` (capture folders; the other layouts carry theirs).

    Raises:
        FileNotFoundError: no layout of posed frames in ``folder``.
        PoseError: a frame without its pose, or a pose that is not camera-to-world rigid.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"scan.input {folder} is not a folder")
    if is_capture_folder(folder):
        poses = _folder_poses(folder)
        frames = capture_frames(folder, depth_scale, intrinsics)
        missing = [frame.id for frame in frames if frame.id not in poses]
        if missing:
            raise PoseError(f"{folder}: {len(missing)} frame(s) without a pose ({', '.join(missing[:5])}"
                            f"{', ...' if len(missing) > 5 else ''}): every frame of a scan needs one")
        return [PosedFrame(frame, poses[frame.id]) for frame in frames]
    if all((folder / name).is_file() for name in ("rgb.txt", "depth.txt", "groundtruth.txt")):
        return _tum_frames(folder)
    if any(p.name.endswith(".pose.txt") for p in folder.iterdir()):
        return _seven_scenes_frames(folder)
    if all((folder / name).exists() for name in ("rgb.mp4", "depth", "odometry.csv", "camera_matrix.csv")):
        return _stray_frames(folder)
    raise FileNotFoundError(f"{folder}: no posed frames: a capture folder with poses.json or poses.txt, a TUM RGB-D "
                            "sequence (rgb.txt, depth.txt, groundtruth.txt), a 7-Scenes sequence "
                            "(frame-NNNNNN.color.png, .depth.png, .pose.txt) or a Stray Scanner export (rgb.mp4, "
                            "depth/, odometry.csv, camera_matrix.csv)")
