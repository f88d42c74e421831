"""Real spherical harmonics and the compression of a sampled hemisphere (Genevaux et al.
2006, sec. 4).

- :func:`real_sh`: the orthonormal real basis y_l^m (eq. 7) of the complex Y_l^m (eq. 4),
  evaluated as polynomials of the Cartesian direction (x, y, z) (eqs. 5-6), by the
  associated Legendre recurrence in z and (x + i y)^m, so no angle is ever computed.
- :func:`view_directions`: the direction set S_d^2 of the paper, a regular subdivision of
  (theta, phi) over the outer hemisphere (sec. 4.2: "regular subdivision of the two angular
  parameters"); ``rings`` polar rings at (a + 1/2) dtheta times ``2 rings`` azimuths.
- :func:`projection_matrix`: M of eq. 10, M_ij = int_S2 y_i B_j ds, with B_j the bilinear
  hat functions in (theta, phi) of eq. 8 (held constant from the first ring to the pole and
  from the last ring to the equator), the lower hemisphere completed by mirroring (sec. 4.2,
  after Sloan et al. 2003): f(x, y, -z) = f(x, y, z). Mirroring makes every coefficient with
  l + m odd vanish (y_l^m(x, y, -z) = (-1)^(l+m) y_l^m), so only the (L+1)(L+2)/2 even ones
  are stored (45 of 81 at order 8). Computed once per direction set (Gauss-Legendre
  quadrature between the hat functions' knots, exact up to ~1e-7), then compressing a
  sample is one matrix product (eq. 10).
- :func:`window`: the semi-Gaussian low-pass weights of sec. 4.3 against ringing (Gibbs).

Example:
    >>> d = torch.tensor([[0.0, 0.0, 1.0]])
    >>> real_sh(d, 1).shape
    torch.Size([1, 4])
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

MAX_ORDER = 8
"""Highest band l the method stores (the paper's hardware limit and its figures' order)."""


def num_coeffs(order: int) -> int:
    """(L + 1)^2 real SH up to band L."""
    return (order + 1) ** 2


def sh_index(l: int, m: int) -> int:  # noqa: E741 (the paper's notation)
    """Position of y_l^m in the basis vector: l^2 + l + m."""
    return l * l + l + m


def even_indices(order: int) -> torch.Tensor:
    """(K,) positions of the y_l^m with l + m even (symmetric under z -> -z), in order."""
    return torch.tensor([sh_index(l, m) for l in range(order + 1) for m in range(-l, l + 1)
                         if (l + m) % 2 == 0], dtype=torch.int64)


def even_bands(order: int) -> torch.Tensor:
    """(K,) band l of each coefficient of :func:`even_indices` (for the window)."""
    return torch.tensor([l for l in range(order + 1) for m in range(-l, l + 1)
                         if (l + m) % 2 == 0], dtype=torch.int64)


def num_even(order: int) -> int:
    """(L + 1)(L + 2) / 2 mirrored-hemisphere coefficients up to band L."""
    return (order + 1) * (order + 2) // 2


def _real_sh_terms(d: torch.Tensor, order: int, even_only: bool) -> dict[int, torch.Tensor]:
    """The y_l^m of :func:`real_sh` by their positions l^2 + l + m (``even_only``: only
    those with l + m even; the odd ones are not formed)."""
    if not 0 <= order <= MAX_ORDER:
        raise ValueError(f"real_sh: order must be in [0, {MAX_ORDER}], got {order}")
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out: dict[int, torch.Tensor] = {}
    # Re / Im of (x + i y)^m
    cm, sm = [torch.ones_like(x)], [torch.zeros_like(x)]
    for _ in range(order):
        c, s = cm[-1], sm[-1]
        cm.append(c * x - s * y)
        sm.append(c * y + s * x)
    for m in range(order + 1):
        q_mm = (-1.0) ** m * float(np.prod(np.arange(1, 2 * m, 2))) if m else 1.0
        q_prev2, q_prev = None, torch.full_like(z, q_mm)
        for l in range(m, order + 1):  # noqa: E741
            if l == m:
                q = q_prev
            elif l == m + 1:
                q = (2 * m + 1) * z * q_prev
            else:
                q = ((2 * l - 1) * z * q_prev - (l + m - 1) * q_prev2) / (l - m)
            if l > m:
                q_prev2, q_prev = q_prev, q
            if even_only and (l + m) % 2:
                continue
            k = math.sqrt((2 * l + 1) / (4 * math.pi)
                          * math.exp(math.lgamma(l - m + 1) - math.lgamma(l + m + 1)))
            if m == 0:
                out[sh_index(l, 0)] = k * q
            else:
                out[sh_index(l, m)] = (math.sqrt(2.0) * k) * q * cm[m]
                out[sh_index(l, -m)] = (math.sqrt(2.0) * k) * q * sm[m]
    return out


def real_sh(d: torch.Tensor, order: int) -> torch.Tensor:
    """Orthonormal real spherical harmonics of unit directions (eqs. 4-7).

    y_l^0 = K_l^0 P_l^0(z); y_l^m = sqrt(2) K_l^m P_l^m(z) Re((x + iy)^m) / sin^m and
    y_l^-m = sqrt(2) K_l^m P_l^m(z) Im((x + iy)^m) / sin^m for m > 0 (eq. 7, Condon-Shortley
    phase included), written with Q_l^m = P_l^m / sin^m theta, a polynomial in z:
    Q_m^m = (-1)^m (2m - 1)!!, Q_{m+1}^m = (2m + 1) z Q_m^m,
    (l - m) Q_l^m = (2l - 1) z Q_{l-1}^m - (l + m - 1) Q_{l-2}^m. So every y is a polynomial
    of x, y, z (eq. 6), as the paper evaluates them.

    Args:
        d: (..., 3) unit directions.
        order: highest band L (0..8).

    Returns:
        (..., (L + 1)^2) values, y_l^m at l^2 + l + m.
    """
    out = _real_sh_terms(d, order, even_only=False)
    return torch.stack([out[i] for i in range(num_coeffs(order))], -1)


def real_sh_even(d: torch.Tensor, order: int) -> torch.Tensor:
    """(..., K) the mirror-symmetric (l + m even) basis functions of :func:`real_sh`, in the
    order of :func:`even_indices` (the same values; the odd ones are never formed)."""
    out = _real_sh_terms(d, order, even_only=True)
    return torch.stack([out[i] for i in even_indices(order).tolist()], -1)


def view_angles(rings: int) -> tuple[np.ndarray, np.ndarray]:
    """(rings,) polar angles (a + 1/2) pi / (2 rings) and (2 rings,) azimuths
    (b + 1/2) pi / rings of the direction set (float64)."""
    theta = (np.arange(rings) + 0.5) * (0.5 * np.pi / rings)
    phi = (np.arange(2 * rings) + 0.5) * (np.pi / rings)
    return theta, phi


def view_directions(rings: int) -> torch.Tensor:
    """(J, 3) float32 local view directions of the outer hemisphere (z = normal),
    J = 2 rings^2, ring-major: j = a * 2 rings + b (the paper's 2048 is ``rings = 32``)."""
    theta, phi = view_angles(rings)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
    return torch.from_numpy(d.reshape(-1, 3).astype(np.float32))


def _hat_weights(x: np.ndarray, knots: np.ndarray, periodic: float | None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear hat functions on ``knots`` at points ``x``: the two knots (i0, i1) and the
    weight of i1; held constant outside the knots, or wrapped with period ``periodic``."""
    n = len(knots)
    step = knots[1] - knots[0]
    pos = (x - knots[0]) / step
    if periodic is not None:
        i0 = np.floor(pos).astype(np.int64)
        f = pos - i0
        return i0 % n, (i0 + 1) % n, f
    pos = np.clip(pos, 0.0, n - 1.0)
    i0 = np.minimum(np.floor(pos).astype(np.int64), n - 2) if n > 1 else np.zeros_like(pos,
                                                                                        np.int64)
    f = pos - i0 if n > 1 else np.zeros_like(pos)
    return i0, np.minimum(i0 + 1, n - 1), f


@functools.lru_cache(maxsize=8)
def projection_matrix(rings: int, order: int = MAX_ORDER, gauss: int = 4) -> torch.Tensor:
    """M of eq. 10 for the direction set of :func:`view_directions`, mirrored lower
    hemisphere, even coefficients only: W = M R compresses the (J, C) samples R of one
    surface sample into (K, C) weights (K = :func:`num_even`).

    M_kj = int_S2 y_k B_j ds = 2 int_H+ y_k B_j ds (mirroring), integrated with ``gauss``
    Gauss-Legendre points in theta and in phi on every interval between the hat functions'
    knots (the integrand is smooth there).

    Returns:
        (K, J) float32 (computed in float64 once per ``rings``, ``order``).
    """
    theta_k, phi_k = view_angles(rings)
    gx, gw = np.polynomial.legendre.leggauss(gauss)

    def rule(breaks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a, b = breaks[:-1, None], breaks[1:, None]
        x = 0.5 * (a + b) + 0.5 * (b - a) * gx
        w = 0.5 * (b - a) * gw
        return x.ravel(), np.broadcast_to(w, x.shape).ravel()

    tq, tw = rule(np.concatenate([[0.0], theta_k, [0.5 * np.pi]]))
    pq, pw = rule(np.concatenate([phi_k, [phi_k[0] + 2 * np.pi]]))
    ti0, ti1, tf = _hat_weights(tq, theta_k, None)
    pi0, pi1, pf = _hat_weights(pq, phi_k, 2 * np.pi)
    tt, pp = np.meshgrid(tq, pq, indexing="ij")  # (Qt, Qp)
    d = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
    y = real_sh_even(torch.from_numpy(d), order).numpy()  # (Qt, Qp, K)
    w = 2.0 * (tw * np.sin(tq))[:, None] * pw[None, :]  # mirroring doubles it
    yw = y * w[..., None]
    nphi = len(phi_k)
    m = np.zeros((y.shape[-1], len(theta_k) * nphi))
    for ti, twt in ((ti0, 1.0 - tf), (ti1, tf)):
        for pi, pwt in ((pi0, 1.0 - pf), (pi1, pf)):
            col = ti[:, None] * nphi + pi[None, :]  # (Qt, Qp)
            wt = twt[:, None] * pwt[None, :]
            np.add.at(m.T, col.ravel(), (yw * wt[..., None]).reshape(-1, y.shape[-1]))
    return torch.from_numpy(m.astype(np.float32))


WINDOWS = ("gauss", "none")


def window(order: int, kind: str = "gauss", width: float = 1.0) -> torch.Tensor:
    """Per-coefficient weights (K,) of the even basis up to ``order`` (sec. 4.3).

    ``gauss``: the semi-Gaussian low-pass exp(-(l / (width (L + 1)))^2 / 2), which damps
    the highest bands and with them the Gibbs ringing of the truncated series; larger
    ``width`` blurs less. ``none``: the plain truncation (a box filter in frequency).
    """
    bands = even_bands(order).double()
    if kind == "none":
        return torch.ones(len(bands))
    if kind != "gauss":
        raise ValueError(f"window: kind must be one of {WINDOWS}, got {kind!r}")
    return torch.exp(-0.5 * (bands / (width * (order + 1))) ** 2).float()


__all__ = ["MAX_ORDER", "WINDOWS", "even_bands", "even_indices", "num_coeffs", "num_even",
           "projection_matrix", "real_sh", "real_sh_even", "sh_index", "view_angles",
           "view_directions", "window"]
