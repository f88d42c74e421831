"""Refractive flow: where on a background plane each object pixel sees, and how blurred.

TOM-Net (Chen, Li, Wong: "TOM-Net: Learning Transparent Object Matting from a Single Image",
CVPR 2018) describes a transparent object in front of a background image by an object mask,
an attenuation and a *refractive flow*: for each object pixel, the offset in the image from
that pixel to the background pixel whose light it shows. Their data are smooth glass; here
the same definition for rough glass, from the lobes of the matte (:mod:`.record`):

- the background is a plane perpendicular to the camera's view axis f, at ``distance``
  behind the camera's target point t0: {X : f . X = f . (t0 + distance f)};
- each object sub-pixel's *main exit lobe* is the transmitted lookup with the largest energy
  (the background lookups of uncovered sub-pixels and the front reflection excluded: a lookup
  from the pixel's own front point heading out of the surface); its ray o + s w (origin o on
  the object, the exit point, and direction w) meets the plane at X = o + s w,
  s = f . (P0 - o) / (f . w), projected by the camera to the continuous pixel position x(w)
  (:func:`torchrefract.geometry.camera.project`);
- ``flow`` = x(w) - the pixel's center, in pixels (x to the right, y down): TOM-Net's flow;
- ``flow_cov``: the lobe's footprint on the plane, in pixels^2 ((xx, xy, yy)): an SG lobe
  exp(k (cos - 1)) ~ exp(-k theta^2 / 2) spreads its direction by 1/k per tangent axis
  (u, v), so its image is J diag(1/k, 1/k) J^T with J = (dx/du, dx/dv) (central differences
  in float64); a plain lobe (k = inf) has none. With n x n supersampling the pixel's
  values are the mean over its covered sub-pixels and the covariance is the total one (the
  sub-pixels' mean covariance plus the spread of their positions);
- ``flow_valid``: the fraction of the pixel's sub-pixels whose main lobe meets the plane in
  front of it (f . w > 0); flow and covariance are averaged over those only, 0 elsewhere.
"""

from __future__ import annotations

import numpy as np
import torch

from torchrefract.geometry.camera import camera_frame, project, projection_params
from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.matte.record import Entries
from torchrefract.optics.smooth import tangent_frame


def main_lobes(entries: Entries, g: GBuffer) -> tuple[torch.Tensor, torch.Tensor]:
    """Per object sub-pixel, the index of its main exit lobe among ``entries`` (module
    docstring). Returns (S,) sub-pixel indices and (S,) entry indices."""
    b, hs, ws = g.shape
    sub = entries.sub
    covered = g.front.mask.reshape(-1)[sub]
    p1 = g.front.position.reshape(-1, 3)[sub]
    n1 = g.front.normal.reshape(-1, 3)[sub]
    d = g.ray_dir.reshape(-1, 3)[sub]
    n_eye = torch.where(((n1 * d).sum(-1) > 0)[:, None], -n1, n1)  # facing the eye
    at_p1 = (entries.origin - p1).norm(dim=-1) <= 1e-5 * (1.0 + p1.norm(dim=-1))
    reflection = at_p1 & ((entries.direction * n_eye).sum(-1) > 0)
    transmitted = covered & ~reflection
    if not bool(transmitted.any()):
        return torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long)
    cand = transmitted.nonzero().squeeze(1)
    e = entries.weight[cand].mean(-1).double()
    s = sub[cand]
    best = torch.full((b * hs * ws,), -1.0, dtype=torch.float64).scatter_reduce(
        0, s, e, "amax", include_self=True)
    top = e >= best[s]
    # one per sub-pixel (the first of ties)
    cand, s = cand[top], s[top]
    first = torch.ones_like(s, dtype=torch.bool)
    order = torch.argsort(s, stable=True)
    ss = s[order]
    first_sorted = torch.ones_like(ss, dtype=torch.bool)
    first_sorted[1:] = ss[1:] != ss[:-1]
    first[order] = first_sorted
    return s[first], cand[first]


def _plane_points(entries: Entries, j: torch.Tensor, bi: torch.Tensor, cameras,
                  distance: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where the lookups ``j`` (of views ``bi``) meet each view's plane, in its pixels (S, 2),
    the covariance (S, 3: xx, xy, yy) their lobes' spread maps to there (the projection's
    Jacobian by central differences across the lobe axis), and whether they meet it
    (S,) bool: in front of the origin, not parallel."""
    o = entries.origin[j].double()
    wdir = torch.nn.functional.normalize(entries.direction[j].double(), dim=-1)
    k = entries.sharpness[j].double()
    frames = [camera_frame(c) for c in cameras]
    f = torch.tensor(np.stack([fr[3] for fr in frames]), dtype=torch.float64)[bi]  # (S, 3)
    p0 = torch.tensor([list(c.target) for c in cameras], dtype=torch.float64)[bi] \
        + distance * f
    params = torch.stack([projection_params(c) for c in cameras]).double()[bi]  # (S, 16)

    def hit(dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        den = (dirs * f).sum(-1)
        ok = den > 1e-6
        sdist = ((p0 - o) * f).sum(-1) / torch.where(ok, den, torch.ones_like(den))
        ok = ok & (sdist > 0)
        xw = o + sdist[:, None] * dirs
        xy, _ = project(xw[:, None, :], params)  # (S, 1, 2): one point per row's camera
        return xy[:, 0], ok

    pos, ok = hit(wdir)
    u, v = tangent_frame(wdir)
    eps = 1e-4
    var = torch.where(torch.isfinite(k) & (k < 1e29), 1.0 / k.clamp(min=1e-12),
                      torch.zeros_like(k))
    cols = []
    for t in (u, v):
        xp, okp = hit(torch.nn.functional.normalize(wdir + eps * t, dim=-1))
        xm, okm = hit(torch.nn.functional.normalize(wdir - eps * t, dim=-1))
        ok = ok & okp & okm
        cols.append((xp - xm) / (2 * eps))  # (S, 2)
    ju, jv = cols
    cov = var[:, None] * torch.stack([ju[:, 0] ** 2 + jv[:, 0] ** 2,
                                      ju[:, 0] * ju[:, 1] + jv[:, 0] * jv[:, 1],
                                      ju[:, 1] ** 2 + jv[:, 1] ** 2], -1)  # (S, 3)
    return pos, cov, ok


def plane_flow(entries: Entries, g: GBuffer, cameras, distance: float,
               shape: tuple[int, int, int]) -> dict[str, torch.Tensor]:
    """The ``flow``, ``flow_cov`` and ``flow_valid`` passes (module docstring).

    Args:
        entries: the recorded lookups (:func:`torchrefract.matte.record.weights`).
        g: the G-buffer (sub-pixel grid).
        cameras: the B scenes' cameras.
        distance: the plane's distance behind each camera's target along its view axis.
        shape: (B, H, W) pixels.

    Returns:
        name -> (B, H, W, C): ``flow`` (2), ``flow_cov`` (3), ``flow_valid`` (1).
    """
    b, h, w = shape
    n = g.supersample
    _, hs, ws = g.shape
    s, j = main_lobes(entries, g)
    out_pos = torch.zeros(b * h * w, 2, dtype=torch.float64)
    out_sec = torch.zeros(b * h * w, 3, dtype=torch.float64)  # E[x x^T] parts, then cov
    out_cnt = torch.zeros(b * h * w, dtype=torch.float64)
    if s.numel():
        bi = s // (hs * ws)
        y, x = (s // ws) % hs, s % ws
        pix = bi * h * w + (y // n) * w + (x // n)
        pos, cov, ok = _plane_points(entries, j, bi, cameras, distance)
        okf = ok.double()
        pos = torch.where(ok[:, None], pos, torch.zeros_like(pos))
        cov = torch.where(ok[:, None], cov, torch.zeros_like(cov))
        second = cov + torch.stack([pos[:, 0] ** 2, pos[:, 0] * pos[:, 1], pos[:, 1] ** 2], -1)
        out_pos.index_add_(0, pix, pos * okf[:, None])
        out_sec.index_add_(0, pix, second * okf[:, None])
        out_cnt.index_add_(0, pix, okf)
    c = out_cnt.clamp(min=1.0)[:, None]
    mean = out_pos / c
    sec = out_sec / c
    cov = sec - torch.stack([mean[:, 0] ** 2, mean[:, 0] * mean[:, 1], mean[:, 1] ** 2], -1)
    # centers of the pixels (x + 0.5, y + 0.5)
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64),
                            torch.arange(w, dtype=torch.float64), indexing="ij")
    center = torch.stack([xx + 0.5, yy + 0.5], -1).reshape(1, h * w, 2).expand(b, -1, -1)
    has = out_cnt > 0
    flow = torch.where(has[:, None], mean - center.reshape(-1, 2), torch.zeros_like(mean))
    cov = torch.where(has[:, None], cov, torch.zeros_like(cov))
    cov[:, 0] = cov[:, 0].clamp(min=0.0)
    cov[:, 2] = cov[:, 2].clamp(min=0.0)
    valid = out_cnt / (n * n)
    out = {"flow": flow.view(b, h, w, 2), "flow_cov": cov.view(b, h, w, 3),
           "flow_valid": valid.view(b, h, w, 1)}
    return {k: torch.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0).float()
            for k, v in out.items()}


__all__ = ["main_lobes", "plane_flow"]
