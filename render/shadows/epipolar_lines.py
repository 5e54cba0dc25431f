"""The pattern of epipolar lines a shadow sweep samples (:mod:`render.shadows.epipolar`).

For each (image, light) pair, lines fan out from the epipole (the light's image) over the
image, sampled at about one pixel; the sweep's table holds one row per line (two padded
rows past the last) and one column per sample (a column before the first, which sees
nothing). These helpers build the pattern and map pixels into the table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["EpipolarLines", "make_lines", "table_row_lines", "pattern_coords", "table_nodes"]


@dataclass(frozen=True)
class EpipolarLines:
    """The epipolar sampling pattern of each (image, light), all ``(N,)`` for N = B*L."""

    epipole: Tensor  # (N, 2) pixel coordinates of the light's image
    forward: Tensor  # (N,) bool: light in front of the camera (sweep outwards)
    periodic: Tensor  # (N,) bool: epipole inside the image (lines all around)
    theta0: Tensor  # (N,) angle of line 0
    dtheta: Tensor  # (N,) angle between lines
    r_min: Tensor  # (N,) distance of the nearest image point to the epipole
    r_max: Tensor  # (N,) distance of the farthest image point
    dr: Tensor  # (N,) distance between samples
    num_lines: int
    num_samples: int

    def select(self, key) -> "EpipolarLines":
        """Every field indexed by ``key``: a slice or index tensor of pairs, or
        ``(slice(None), None)`` for ``(N, 1)`` fields that broadcast against pixels."""
        fields = ("epipole", "forward", "periodic", "theta0", "dtheta", "r_min", "r_max", "dr")
        return EpipolarLines(*(getattr(self, f)[key] for f in fields), self.num_lines, self.num_samples)

    def radius(self, k: Tensor) -> Tensor:
        """Distance to the epipole of sample index ``k`` ``(N, ...)``."""
        shape = (-1,) + (1,) * (k.dim() - 1)
        fwd = self.r_min.view(shape) + k * self.dr.view(shape)
        back = self.r_max.view(shape) - k * self.dr.view(shape)
        return torch.where(self.forward.view(shape), fwd, back)


def make_lines(light_position: Tensor, K: Tensor, height: int, width: int, spacing: float) -> EpipolarLines:
    """Sampling pattern covering the image for each light; ``light_position (N, 3)``, ``K (N, 3, 3)``."""
    dtype = light_position.dtype
    lz = light_position[:, 2]
    # Guard: a light in the camera plane (z = 0) projects to infinity; nudge it
    # to a tiny |z| so the lines become (nearly) parallel instead of undefined.
    eps_z = 1e-4 * light_position.norm(dim=-1) + torch.finfo(dtype).tiny ** 0.5
    forward = lz >= 0
    z_eff = torch.where(lz.abs() < eps_z, torch.where(forward, eps_z, -eps_z), lz)
    projected = torch.einsum("nij,nj->ni", K, light_position)
    epipole = projected[:, :2] / z_eff[:, None]

    corners = torch.tensor(
        [[0.0, 0.0], [width - 1.0, 0.0], [0.0, height - 1.0], [width - 1.0, height - 1.0]],
        dtype=dtype, device=light_position.device,
    )
    to_corner = corners[None] - epipole[:, None]  # (N, 4, 2)
    r_corner = to_corner.norm(dim=-1)
    r_max = r_corner.amax(-1)
    upper = corners[3]
    inside = ((epipole >= 0) & (epipole <= upper)).all(-1)
    nearest = torch.minimum(torch.maximum(epipole, torch.zeros_like(upper)), upper)
    r_min = torch.where(inside, torch.zeros_like(r_max), (epipole - nearest).norm(dim=-1))

    # Angular span of the image seen from an outside epipole: corner angles
    # relative to the direction of the image centre (no wrap-around possible,
    # the rectangle subtends less than pi from outside).
    to_centre = corners.mean(0)[None] - epipole
    theta_c = torch.atan2(to_centre[:, 1], to_centre[:, 0])
    cross = to_centre[:, None, 0] * to_corner[..., 1] - to_centre[:, None, 1] * to_corner[..., 0]
    dot = (to_centre[:, None] * to_corner).sum(-1)
    rel = torch.atan2(cross, dot)
    span = torch.where(inside, torch.full_like(r_max, 2 * math.pi), rel.amax(-1) - rel.amin(-1))
    theta0 = torch.where(inside, torch.full_like(r_max, -math.pi), theta_c + rel.amin(-1))

    with torch.no_grad():
        needed = torch.stack([torch.ceil(span * r_max / spacing).amax(),
                              torch.ceil((r_max - r_min) / spacing).amax()]).tolist()  # one host sync
    num_lines = max(int(needed[0]) + 1, 2)
    num_samples = max(int(needed[1]) + 1, 2)
    dtheta = torch.where(inside, span / num_lines, span / (num_lines - 1))
    # Guard: an image of one pixel has r_max == r_min; keep the step non-zero.
    dr = ((r_max - r_min) / (num_samples - 1)).clamp_min(torch.finfo(dtype).eps)
    return EpipolarLines(epipole, forward, inside, theta0, dtheta, r_min, r_max, dr, num_lines, num_samples)


def table_row_lines(lines: EpipolarLines, nl: int) -> Tensor:
    """``(N, nl + 2)``: the line index (as a float) of each row of the padded sweep table.

    Rows ``nl`` and ``nl + 1`` are where the interpolation of table_nodes lands past
    the last line: lines 0 and 1 again when the lines go all around the epipole, the
    last line again (a clamp) otherwise.
    """
    index = torch.arange(nl + 2, dtype=lines.dtheta.dtype, device=lines.dtheta.device)
    past = index[nl:]
    wrapped = torch.where(lines.periodic[:, None], past - nl, torch.full_like(past, nl - 1))
    return torch.cat([index[:nl].expand(len(lines.periodic), nl), wrapped], dim=1)


def pattern_coords(lines: EpipolarLines, u: Tensor, v: Tensor, lookback: float) -> tuple[Tensor, Tensor]:
    """Where pixels ``(u, v)`` fall in the pattern, ``lookback`` samples before them:
    ``a`` across lines (line index, fractional) and ``s`` along them (sample index).

    ``lines`` fields broadcast against ``u`` and ``v``; differentiable in both.
    """
    dx, dy = u - lines.epipole[..., 0], v - lines.epipole[..., 1]
    r_pix = (dx * dx + dy * dy).sqrt()
    # The pixel's angle from the pattern's reference direction: from line 0 where the
    # lines span less than pi (outside epipole); from the direction pi past line 0
    # (= -pi) where they go all around, offset by pi into [0, 2 pi].
    periodic = lines.periodic.to(u.dtype)
    base = lines.theta0 + math.pi * periodic
    cos_b, sin_b = torch.cos(base), torch.sin(base)
    across, along = cos_b * dy - sin_b * dx, cos_b * dx + sin_b * dy
    if across.requires_grad or along.requires_grad:
        # atan2 guard: the pixel at the epipole has no direction; any fixed one will
        # do, and atan2's gradient at (0, 0) is 0/0.
        at_epipole = r_pix < 1e-6
        across, along = torch.where(at_epipole, 1.0, across), torch.where(at_epipole, 1.0, along)
    rel = torch.atan2(across, along) + math.pi * periodic
    upper = (lines.num_lines - 1) + periodic  # periodic: index nl is line 0 again (padded row)
    a = torch.minimum((rel / lines.dtheta).clamp_min(0), upper)
    radial = torch.where(lines.forward, r_pix - lines.r_min, lines.r_max - r_pix)
    return a, radial / lines.dr - lookback


def table_nodes(a: Tensor, s: Tensor, ns: int) -> tuple[Tensor, Tensor, Tensor]:
    """The four pattern nodes around pattern coordinates ``a, s (...)`` (see pattern_coords):
    flat indices ``(..., 4)`` into the padded sweep table ``(nl + 2) x (ns + 1)`` of
    :func:`_sweep`, ordered (line, sample) = (0, 0), (0, 1), (1, 0), (1, 1) from the
    lower corner, and the interpolation weights across (``fa``) and along (``fs``)."""
    a0, s0 = a.detach().floor(), s.detach().floor()
    width = ns + 1
    row = a0.long() * width
    col = s0.long() + 1
    col = col.clamp(0, ns), (col + 1).clamp(0, ns)  # column 0: nothing before the first sample
    node = torch.stack([row + col[0], row + col[1], row + (width + col[0]), row + (width + col[1])], dim=-1)
    return node, a - a0, s - s0
