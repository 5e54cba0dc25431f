"""One set of world-frame lights from the per-frame estimates of a posed scan.

Each frame's lights (its record: camera-frame positions and covariances) are mapped to the
world by the frame's pose, ``p_w = R p_c + t`` and ``C_w = R C_c R^T``. The room's lights do
not move while the camera does, so the same light found from several views lands in one
place: the lights are grouped (:func:`group_lights`, brightest first, a frame giving at most
one light to a group), a group is a light of the scan when enough of the frames that found
lights found it (:data:`FuseOptions.min_support`: the count is chosen over the whole scan,
a light one view invents is left out), and its position is the robust, covariance-weighted
mean of its members (:func:`fused_position`).

Its covariance is that mean's, widened by the members' scatter: the frames' own
covariances miss what differs between views (their indirect light, their depth's errors).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["FuseOptions", "WorldLight", "FusedLight", "world_lights", "group_lights", "fused_position", "fuse"]


@dataclass(frozen=True)
class FuseOptions:
    """The fusion's constants (``scan.fuse.NAME`` on the command line).

    Attributes:
        gate: a light joins a group within this many standard deviations (its covariance and
            the group's, summed) of the group's position ...
        gate_floor: ... or within this share of the scene size (covariances of a few
            millimetres would split one light seen with a view's bias).
        min_support: a group is a light of the scan when at least this share of the frames
            that found a light found it (and at least ``min_frames`` frames did).
        min_frames: see ``min_support``.
        robust_scale: the Cauchy scale of the fused mean, in standard deviations of each member.
    """

    gate: float = 3.0
    gate_floor: float = 0.1
    min_support: float = 0.3
    min_frames: int = 2
    robust_scale: float = 2.0

    def __post_init__(self):
        for name in ("gate", "gate_floor", "robust_scale"):
            if not getattr(self, name) > 0:
                raise ValueError(f"scan.fuse.{name} must be > 0, got {getattr(self, name)!r}")
        if not 0 < self.min_support <= 1:
            raise ValueError(f"scan.fuse.min_support must be in (0, 1], got {self.min_support!r}")
        if not (isinstance(self.min_frames, int) and self.min_frames >= 1):
            raise ValueError(f"scan.fuse.min_frames must be an integer >= 1, got {self.min_frames!r}")


@dataclass
class WorldLight:
    """One frame's light in the world: ``position (3,)``, ``cov (3, 3)``, its ``share`` of the
    frame's light, ``intensity (3,)`` in that frame's image units, the ``frame`` index."""

    position: np.ndarray
    cov: np.ndarray
    share: float
    intensity: np.ndarray
    frame: int


@dataclass
class FusedLight:
    """A light of the scan: ``position (3,)`` and ``cov (3, 3)`` in the world, the frames
    that found it (``members``) and ``support`` (their share of the frames that found a light)."""

    position: np.ndarray
    cov: np.ndarray
    members: list[WorldLight] = field(default_factory=list)
    support: float = 0.0


def world_lights(record: dict, pose: np.ndarray, frame: int) -> list[WorldLight]:
    """The lights of one frame's estimation record in the world of ``pose (4, 4)``
    (camera-to-world); none where the record found no light."""
    if not record.get("light_found", bool(record.get("lights"))):
        return []
    R, t = pose[:3, :3], pose[:3, 3]
    out = []
    for light in record["lights"]:
        cov = np.asarray(light.get("position_cov", np.diag(np.square(light.get("position_std", [0.1] * 3)))))
        out.append(WorldLight(R @ np.asarray(light["position"], dtype=np.float64) + t, R @ cov @ R.T,
                              float(light.get("share", 1.0)), np.asarray(light["intensity"], dtype=np.float64), frame))
    return out


def _distance(a: np.ndarray, cov: np.ndarray, b: np.ndarray) -> float:
    # Mahalanobis distance of b from a under cov (regularised).
    d = b - a
    return float(np.sqrt(d @ np.linalg.solve(cov + 1e-12 * np.eye(3), d)))


def group_lights(lights: list[WorldLight], size: float, options: FuseOptions) -> list[FusedLight]:
    """``lights`` grouped, brightest share first: each joins the nearest group within the
    gate (:class:`FuseOptions`) that holds no light of its frame yet, else starts one. A
    group's position is its members' :func:`fused_position` as they join."""
    groups: list[FusedLight] = []
    for light in sorted(lights, key=lambda x: -x.share):
        best, best_distance = None, np.inf
        for group in groups:
            if any(member.frame == light.frame for member in group.members):
                continue
            euclid = float(np.linalg.norm(group.position - light.position))
            sigma = _distance(group.position, group.cov + light.cov, light.position)
            if (sigma <= options.gate or euclid <= options.gate_floor * size) and euclid < best_distance:
                best, best_distance = group, euclid
        if best is None:
            groups.append(FusedLight(light.position.copy(), light.cov.copy(), [light]))
        else:
            best.members.append(light)
            best.position, best.cov = fused_position(best.members, options)
    return groups


def fused_position(members: list[WorldLight], options: FuseOptions) -> tuple[np.ndarray, np.ndarray]:
    """The robust mean ``(3,)`` of the members' positions, each weighted by its inverse
    covariance and by Cauchy weights of its distance (in its own standard deviations) from
    the mean, from the median; and its covariance ``(3, 3)``: the weighted mean's, plus the
    members' weighted scatter over their number (what the views disagree by)."""
    positions = np.stack([m.position for m in members])
    if len(members) == 1:
        return positions[0].copy(), members[0].cov.copy()
    information = [np.linalg.inv(m.cov + 1e-12 * np.eye(3)) for m in members]
    centre = np.median(positions, axis=0)
    for _ in range(10):
        robust = [1 / (1 + (_distance(centre, m.cov, m.position) / options.robust_scale) ** 2) for m in members]
        total = sum(r * info for r, info in zip(robust, information))
        centre = np.linalg.solve(total, sum(r * info @ p for r, info, p in zip(robust, information, positions)))
    weights = np.array(robust) / sum(robust)
    spread = positions - centre
    scatter = (weights[:, None, None] * spread[:, :, None] * spread[:, None, :]).sum(0)
    return centre, np.linalg.inv(total) + scatter / len(members)


def fuse(per_frame: list[list[WorldLight]], size: float, options: FuseOptions | None = None) -> list[FusedLight]:
    """The lights of the scan from each frame's world lights (``per_frame[f]``); ``size``
    the scene's size (metres), brightest first (by their members' median share)."""
    options = options or FuseOptions()
    found = sum(1 for lights in per_frame if lights)
    groups = group_lights([light for lights in per_frame for light in lights], size, options)
    kept = []
    for group in groups:
        frames = len({m.frame for m in group.members})
        group.support = frames / max(found, 1)
        if frames >= options.min_frames and group.support >= options.min_support:
            kept.append(group)
    if not kept and groups:  # a scan of fewer frames than min_frames: its best-supported light, if supported
        best = max(groups, key=lambda g: (g.support, np.median([m.share for m in g.members])))
        kept = [best] if best.support >= options.min_support else []
    return sorted(kept, key=lambda g: -float(np.median([m.share for m in g.members])))
