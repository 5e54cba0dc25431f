"""Light through a rough clear coat: the diffuse layer of glossy plastic.

Glossy plastic, varnished wood and paint are a diffuse layer under a clear
dielectric coat whose reflection is the specular highlight. Light reaches the
diffuse layer only through the coat and leaves it only through the coat, so the
diffuse term is scaled by the coat's transmittance on the way in and on the way
out. For a rough coat (microfacets with a Beckmann distribution of roughness
``a``, Smith masking, the exact Fresnel equations of a dielectric of relative
index ``eta``) the share of light at incidence cosine ``mu`` that enters is

    T(mu) = integral over half vectors h of (1 - F(i.h)) G(i, o) D(h) (i.h) / mu dw_h,

``o`` the refracted direction, and the light the diffuse layer sends back up is
reflected inside the coat again and again, a series summed by
``1 / (1 - R_int)``, ``R_int`` the coat's hemispherical reflectance seen from
inside, all over ``eta^2`` (radiance is compressed by ``eta^2`` on entry). The
diffuse term of a coated pixel is then

    kd * T(n.l) * T(n.v) / (eta^2 (1 - R_int)) * max(0, n.l),

the linear diffuse lobe of physically based renderers' rough plastic. Its
roughness follows from the Blinn-Phong exponent ``s`` that the scene format
gives (the standard correspondence ``s = 2 / a^2 - 2``). ``T`` and ``R_int`` are
found by quadrature once per index of refraction, dtype and device, and read off
a table (:func:`coat_tables`) by bilinear interpolation in ``mu`` and ``log a``;
a renderer reads one row of it per distinct (coat, shininess) pair of a material
(:func:`coat_profile`, then :func:`profile_transmission`: two gathers per pixel).
The same model at a smooth coat (``a -> 0``) is the Fresnel transmittance;
roughness lets more light in at grazing angles (masked reflection is lost to
the reflected lobe) and lowers ``R_int``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from render.geometry import broadcast_shape

__all__ = ["STORED_TABLES", "write_stored_tables", "fresnel_dielectric", "beckmann_g1", "coat_roughness",
           "rough_transmittance", "internal_reflectance", "coat_tables", "coat_eta", "coat_transmission", "CoatProfile", "coat_profile", "profile_transmission"]

ALPHA_RANGE = (0.02, 1.0)  # coat roughness tabulated (Blinn-Phong exponent about 5000 to 0)
TABLE_ALPHAS = 25  # log-spaced
TABLE_COSINES = 65  # uniform in [0, 1]
PROFILE_MAX_ROWS = 4096  # distinct (coat, shininess) pairs a CoatProfile tabulates
# coat_tables at the default coat (Material.coat_f0 = 0.04), found once by write_stored_tables and
# read instead of the quadrature: the quadrature takes 0.5 s in every fresh process on one thread
# (an estimator's worker judging a coat, 2026-12-07), reading the file about a millisecond.
STORED_TABLES = Path(__file__).with_name("coat_tables_f0_0.04.npz")


def fresnel_dielectric(cosine: Tensor, eta: float) -> Tensor:
    """Unpolarised Fresnel reflectance of light arriving at ``cosine`` (> 0) on a
    dielectric interface of relative index ``eta`` (inside over outside; < 1 seen
    from inside, with total internal reflection). Shapes follow ``cosine``."""
    sin2_t = (1 - cosine * cosine).clamp_min(0) / (eta * eta)
    cos_t = (1 - sin2_t).clamp_min(0).sqrt()
    r_s = (cosine - eta * cos_t) / (cosine + eta * cos_t)
    r_p = (eta * cosine - cos_t) / (eta * cosine + cos_t)
    return torch.where(sin2_t >= 1, torch.ones_like(cosine), 0.5 * (r_s * r_s + r_p * r_p))


def beckmann_g1(cosine: Tensor, alpha: Tensor | float) -> Tensor:
    """Smith masking of a Beckmann surface of roughness ``alpha`` seen at ``cosine``
    (Walter et al. 2007's rational approximation; 0 at or below the horizon)."""
    tangent = (1 - cosine * cosine).clamp_min(0).sqrt() / cosine.clamp_min(1e-12)
    a = 1 / (alpha * tangent).clamp_min(1e-12)
    rational = (3.535 * a + 2.181 * a * a) / (1 + 2.276 * a + 2.577 * a * a)
    return torch.where(a >= 1.6, torch.ones_like(a), rational) * (cosine > 0)


def coat_roughness(shininess: Tensor) -> Tensor:
    """Beckmann roughness ``sqrt(2 / (s + 2))`` of a Blinn-Phong exponent ``s``."""
    return (2 / (shininess + 2)).sqrt()


def _half_vector_quadrature(mu: Tensor, alpha: Tensor, eta: float, transmitted: bool, n_theta: int = 48,
                            n_phi: int = 24) -> Tensor:
    # (A, M): the share of light at incidence cos mu (M,) on surfaces of roughness alpha (A,)
    # that the interface transmits (or reflects), masking included. Midpoint rule over the
    # half vector's polar angle up to atan(5 alpha) (D is below exp(-25) beyond) and its
    # azimuth over [0, pi] (the integrand is symmetric about the plane of incidence).
    t_max = torch.atan(5 * alpha)[:, None, None, None]
    theta = ((torch.arange(n_theta, dtype=mu.dtype, device=mu.device) + 0.5) / n_theta)[:, None] * t_max  # (A, 1, T, 1)
    phi = ((torch.arange(n_phi, dtype=mu.dtype, device=mu.device) + 0.5) / n_phi * math.pi)[None, None, None]
    a = alpha[:, None, None, None]
    m = mu[None, :, None, None]
    sin_i = (1 - m * m).clamp_min(0).sqrt()
    h_x, h_z = theta.sin() * phi.cos(), theta.cos()
    cos_ih = sin_i * h_x + m * h_z  # i = (sin_i, 0, mu)
    if transmitted:
        k = 1 - (1 - cos_ih * cos_ih) / (eta * eta)
        # o = -i / eta + (cos_ih / eta - sqrt(k)) h: its cosine below the surface.
        cos_o = m / eta - (cos_ih / eta - k.clamp_min(0).sqrt()) * h_z
        share = (1 - fresnel_dielectric(cos_ih.clamp_min(1e-12), eta)) * (k > 0)
    else:
        cos_o = 2 * cos_ih * h_z - m
        share = fresnel_dielectric(cos_ih.clamp_min(1e-12), eta)
    tan2 = theta.tan().square()
    density = torch.exp(-tan2 / (a * a)) / (math.pi * a * a * h_z**4)
    masking = beckmann_g1(m.expand_as(cos_ih), a) * beckmann_g1(cos_o, a)
    integrand = share * masking * density * cos_ih.clamp_min(0) / m * (cos_o > 0)
    weight = theta.sin() * (t_max / n_theta) * (2 * math.pi / n_phi)
    return (integrand * weight).sum((2, 3))


def rough_transmittance(mu: Tensor, alpha: Tensor, eta: float) -> Tensor:
    """``T (A, M)``: the share of light at incidence cosine ``mu (M,)`` that enters a
    rough dielectric coat of roughness ``alpha (A,)`` and index ``eta``."""
    return _half_vector_quadrature(mu.clamp_min(1e-4), alpha, eta, transmitted=True)


def internal_reflectance(alpha: Tensor, eta: float, n_cosines: int = 64) -> Tensor:
    """``R_int (A,)``: the hemispherical (cosine-weighted) reflectance of the coat seen
    from inside, for diffuse light from below."""
    mu = (torch.arange(n_cosines, dtype=alpha.dtype, device=alpha.device) + 0.5) / n_cosines
    reflected = _half_vector_quadrature(mu, alpha, 1 / eta, transmitted=False)
    return 2 * (reflected * mu).mean(-1)


@lru_cache(maxsize=16)
def coat_tables(eta: float, dtype: torch.dtype, device: str) -> tuple[Tensor, Tensor]:
    """``(T (A, M), scale (A,))`` at ``A`` log-spaced roughnesses over ``ALPHA_RANGE`` and
    ``M`` uniform cosines in [0, 1]: the transmittance and ``1 / (eta^2 (1 - R_int))``.
    Found in float64 by quadrature (0.2-0.5 s on the 2-core CPU, once per process), or read
    from :data:`STORED_TABLES` at its index of refraction; cached per arguments (``device`` as a
    string: ``str(tensor.device)``), returned in ``dtype`` on ``device``."""
    transmittance, scale = _stored_tables(eta) or _quadrature_tables(eta)
    return transmittance.to(dtype=dtype, device=device), scale.to(dtype=dtype, device=device)


def _quadrature_tables(eta: float) -> tuple[Tensor, Tensor]:
    # coat_tables' values in float64 on the CPU, by quadrature.
    alpha = torch.exp(torch.linspace(math.log(ALPHA_RANGE[0]), math.log(ALPHA_RANGE[1]), TABLE_ALPHAS,
                                     dtype=torch.float64))
    mu = torch.linspace(0, 1, TABLE_COSINES, dtype=torch.float64)
    return rough_transmittance(mu, alpha, eta), 1 / (eta * eta * (1 - internal_reflectance(alpha, eta)))


def _stored_tables(eta: float) -> tuple[Tensor, Tensor] | None:
    # STORED_TABLES' values where they were found for this eta and the tables' current layout; None otherwise.
    if not STORED_TABLES.is_file():
        return None
    with np.load(STORED_TABLES) as stored:
        layout = (TABLE_ALPHAS, TABLE_COSINES, *ALPHA_RANGE)
        if abs(float(stored["eta"]) - eta) > 1e-12 or tuple(stored["layout"].tolist()) != layout:
            return None
        return torch.from_numpy(stored["transmittance"].copy()), torch.from_numpy(stored["scale"].copy())


def write_stored_tables(path: Path = STORED_TABLES, f0: float = 0.04) -> None:
    """Write :func:`coat_tables`' float64 values for a coat of normal-incidence reflectance
    ``f0`` (by quadrature) to ``path``, with the index and the tables' layout they hold
    (``python -c "from render.coat import write_stored_tables; write_stored_tables()"`` after
    a change of the quadrature or the layout; a test checks the shipped file against it)."""
    eta = coat_eta(f0)
    transmittance, scale = _quadrature_tables(eta)
    np.savez(path, eta=np.float64(eta), layout=np.array([TABLE_ALPHAS, TABLE_COSINES, *ALPHA_RANGE], dtype=np.float64),
             transmittance=transmittance.numpy(), scale=scale.numpy())


def coat_eta(f0: float) -> float:
    """The relative index of refraction whose normal-incidence reflectance is ``f0``."""
    root = math.sqrt(f0)
    return (1 + root) / (1 - root)


def coat_transmission(cosine: Tensor, coat: Tensor, shininess: Tensor, f0: float) -> tuple[Tensor, Tensor]:
    """The factor a coat puts on one side of the diffuse term and its derivative with
    respect to ``cosine``: ``1 - coat + coat T(c) sqrt(scale)`` (:func:`coat_tables`;
    the two sides together carry ``scale`` once), ``c`` clamped to [0, 1] (derivative 0
    outside). ``coat`` in [0, 1] is the coat's weight (0: none), ``shininess`` the
    Blinn-Phong exponent that sets its roughness (:func:`coat_roughness`, clamped to
    ``ALPHA_RANGE``), ``f0`` its reflectance at normal incidence. Shapes broadcast.

    Example:
        >>> cosine, coat = torch.tensor([1.0, 0.5]), torch.tensor(1.0)
        >>> [round(x, 2) for x in coat_transmission(cosine, coat, torch.tensor(1e4), 0.04)[0].tolist()]  # smooth
        [1.01, 0.96]
        >>> [round(x, 2) for x in coat_transmission(cosine, coat, torch.tensor(20.0), 0.04)[0].tolist()]  # rough
        [0.94, 0.88]
    """
    table, scale = coat_tables(coat_eta(float(f0)), cosine.dtype, str(cosine.device))
    shape = broadcast_shape(cosine.shape, coat.shape, shininess.shape)
    row, row_weight = _roughness_rows(shininess.to(cosine.dtype))
    row_weight = row_weight.expand(shape)
    row = row.expand(shape)
    at_cos = cosine.clamp(0, 1) * (TABLE_COSINES - 1)
    col = at_cos.detach().floor().nan_to_num(0).clamp(0, TABLE_COSINES - 2)  # a NaN cosine reads row 0, gives NaN
    col_weight = at_cos - col
    col = col.long().expand(shape)
    flat = table.reshape(-1)

    def entry(r: Tensor, c: Tensor) -> Tensor:
        return flat[(r * TABLE_COSINES + c).reshape(-1)].view(shape)

    low = entry(row, col) * (1 - row_weight) + entry(row + 1, col) * row_weight
    high = entry(row, col + 1) * (1 - row_weight) + entry(row + 1, col + 1) * row_weight
    root_scale = _between_rows(scale, row, row_weight).sqrt()
    coated = (low + (high - low) * col_weight) * root_scale
    transmission = 1 - coat + coat * coated
    inside = (cosine > 0) & (cosine < 1)
    slope = torch.where(inside, coat * (high - low) * (TABLE_COSINES - 1) * root_scale, torch.zeros_like(transmission))
    return transmission, slope


def _roughness_rows(shininess: Tensor) -> tuple[Tensor, Tensor]:
    # The table's roughness row below each shininess (long) and the weight of the next.
    log_alpha = coat_roughness(shininess).clamp(*ALPHA_RANGE).log()
    lo, hi = math.log(ALPHA_RANGE[0]), math.log(ALPHA_RANGE[1])
    at_alpha = (log_alpha - lo) / (hi - lo) * (TABLE_ALPHAS - 1)
    row = at_alpha.floor().clamp(0, TABLE_ALPHAS - 2)
    return row.long(), at_alpha - row


def _between_rows(values: Tensor, row: Tensor, weight: Tensor) -> Tensor:
    # values (a table or its scale) interpolated between roughness rows row and row + 1.
    return values[row] * (1 - weight) + values[row + 1] * weight


@dataclass(frozen=True)
class CoatProfile:
    """:func:`coat_transmission` of one material tabulated for fast reuse: ``rows``
    ``(U * TABLE_COSINES,)``, the transmission ``1 - coat + coat T(c) sqrt(scale)`` at
    the table's cosines for each of the ``U`` distinct (coat, shininess) pairs, and
    ``offset``, each pixel's first entry in ``rows`` (long, the shape of
    ``broadcast(coat, shininess)``). Holds no autograd graph of coat or shininess."""

    rows: Tensor
    offset: Tensor


def coat_profile(coat: Tensor, shininess: Tensor, f0: float, dtype: torch.dtype | None = None,
                 max_rows: int = PROFILE_MAX_ROWS) -> CoatProfile | None:
    """The :class:`CoatProfile` of a coat weight and shininess (shapes broadcast; the
    result's ``offset`` has their broadcast shape), in ``dtype`` (default: ``coat``'s),
    or None where they hold more than ``max_rows`` distinct pairs (a shininess texture:
    use :func:`coat_transmission`). Costs one sort of the pixels."""
    dtype = coat.dtype if dtype is None else dtype
    shape = broadcast_shape(coat.shape, shininess.shape)
    # Pairs numbered by the distinct values of each (three 1-D sorts: far faster than
    # a sort of the pairs as rows).
    coats, coat_index = torch.unique(coat.detach().to(dtype), return_inverse=True)
    shininesses, shininess_index = torch.unique(shininess.detach().to(dtype), return_inverse=True)
    pair_index = (coat_index * shininesses.numel()).expand(shape) + shininess_index.expand(shape)
    pairs, inverse = torch.unique(pair_index, return_inverse=True)
    distinct = torch.stack([coats[pairs // shininesses.numel()], shininesses[pairs % shininesses.numel()]], -1)
    if distinct.shape[0] > max_rows:
        return None
    table, scale = coat_tables(coat_eta(float(f0)), dtype, str(coat.device))
    row, weight = _roughness_rows(distinct[:, 1])
    transmittance = _between_rows(table, row, weight[:, None])  # (U, M)
    root_scale = _between_rows(scale, row, weight).sqrt()
    weight_of_coat = distinct[:, :1]
    rows = 1 - weight_of_coat + weight_of_coat * transmittance * root_scale[:, None]
    return CoatProfile(rows.reshape(-1), (inverse * TABLE_COSINES).view(shape))


def profile_transmission(cosine: Tensor, profile: CoatProfile) -> tuple[Tensor, Tensor]:
    """:func:`coat_transmission` read off a :class:`CoatProfile`: the same values
    (to rounding) in about a third of the operations; differentiable in ``cosine``.
    ``cosine`` broadcasts against ``profile.offset``."""
    at_cos = cosine.clamp(0, 1) * (TABLE_COSINES - 1)
    col = at_cos.detach().floor().nan_to_num(0).clamp(max=TABLE_COSINES - 2)  # NaN in, NaN out, no stray index
    index = profile.offset + col.long()
    low, high = profile.rows[index], profile.rows[index + 1]
    step = high - low
    transmission = low + step * (at_cos - col)
    inside = (cosine > 0) & (cosine < 1)
    return transmission, torch.where(inside, step * (TABLE_COSINES - 1), torch.zeros_like(step))
