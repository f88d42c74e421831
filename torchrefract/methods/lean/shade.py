"""``lean`` and ``gsr`` over the object pixels of a batch (package docstring).

Steps 1-2 (front lobes, cone tracing), the exit rule, the internal bounces, the lights and
absorption are ``rousiers``' own functions; what differs is step 3, the back layer over the
footprint (LEAN moments, K Gaussians for ``gsr``: :mod:`.moments`), and step 5: the exit
lobes, one per subdivision and roughness node, anisotropic (:mod:`.lobes`) and read by EWA
taps (:mod:`torchrefract.lighting.ewa`).

Where :mod:`torchrefract.shading.fused_lean` covers the options and no gradient is wanted,
the same steps run as one native kernel (kernels/csrc/lean.c); this tensor code is the
reference and the differentiable path.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.lighting.ewa import ewa_radiance
from torchrefract.lighting.lights import Lighting, incident_radiance_sg
from torchrefract.methods.lean.lobes import (
    incidence_frame,
    paper_covariance,
    ray_covariance,
)
from torchrefract.methods.lean.moments import (
    Footprint,
    footprint_sums,
    gaussians,
    lean_mips,
    reads_no_moments,
    separation,
    uniform_footprint,
)
from torchrefract.methods.rousiers.cone import Cone, bounding_normals, trace_cone
from torchrefract.methods.rousiers.exit import ExitInterface, exit_interface, exit_lobe
from torchrefract.methods.rousiers.lobes import FrontLobes, front_lobes, spread_energies
from torchrefract.methods.rousiers.pixels import Pixels, object_pixels
from torchrefract.methods.rousiers.shade import finish, object_passes
from torchrefract.optics import microfacet as mf
from torchrefract.optics.cov2 import psd2
from torchrefract.optics.exit_rule import clamp_to_critical
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.sgfit import load_sg_table
from torchrefract.optics.smooth import dot, normalize
from torchrefract.shading import fused_lean
from torchrefract.shading.background import background


@dataclass
class _Lobe:
    """One exit lobe of N pixels: its interface, axis, the table's sharpness (the
    microfacet part) and the exit rule's weight; its share of the footprint, subdivision
    j and roughness alpha; what its interface reflects inside (for the bounces)."""

    xi: ExitInterface
    axis: torch.Tensor
    k: torch.Tensor
    energy: torch.Tensor
    share: torch.Tensor
    j: int
    alpha: torch.Tensor
    reflected: torch.Tensor


def render_lean(g: GBuffer, lighting: Lighting, materials: MaterialBatch, options,
                subdivisions: int = 1, spread: str = "rays"
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Shade a G-buffer with Dai and Wyman's rough refraction: ``subdivisions`` = 1 is
    LEAN, more is GSR; ``spread`` the exit lobes' geometric width (:mod:`.lobes`).

    Returns radiance (B, H, W, 3) and the passes of ``rousiers`` (``exit_found``, ``tir``,
    ``lobe_sigma``: the per-axis spread sqrt(trace / 2) of the transmitted lobes' mixture,
    ``footprint``; with bounces theirs)."""
    b, h, w = g.shape
    radiance = background(g, lighting)
    done = fused_lean.lean(g, lighting, materials, options, radiance, subdivisions, spread)
    if done is not None:  # the fused kernel ran (shading.fused_lean says where it does)
        return done
    idx = g.object_index()
    bounce = options.bounces.enabled
    if idx.numel() == 0:
        return radiance.view(b, h, w, 3), object_passes(g, idx, bounce, None, None)
    table = load_sg_table()
    px = object_pixels(g, materials)
    front = front_lobes(table, px.view, px.n1, px.cos1, px.ior, px.alpha, px.dist)
    cone = trace_cone(g, px.bi, px.p1, front.p_t1, front.k_t1, options)
    if reads_no_moments(subdivisions, spread, materials.has_maps):
        fp = uniform_footprint(px.alpha)  # the moments of one roughness: its own
    else:  # (one roughness per view: its moments from it, not through the mips)
        sums = footprint_sums(lean_mips(g, materials, subdivisions, materials.has_maps),
                              subdivisions, px.bi, cone.xy_c, cone.major, cone.ext,
                              cone.level, materials.roughness[px.bi])
        fp = gaussians(g, px.bi, sums)
    mode = "split" if bounce else options.tir
    if spread == "paper":
        lobes, normals, weight = _lobes(g, table, px, front, cone, fp, materials, options,
                                        mode, exact=False, reflected=bounce)
        # the bounces continue from the lobes' mean normal
        xi = exit_interface(g, px, front, cone.ex, normalize(
            (weight[..., None] * normals).sum(1)), None, materials)
        covs, variance = _paper_covariances(px, front.p_t1, cone, fp, lobes)
        l_trans = _read(lighting, px, lobes, covs, options)
        sectors = _reflected(lobes)
        reflected = lambda _: sectors  # noqa: E731  (the lobes' own)
    else:  # the mixture's center and the bounces: the exact exit normal
        xi = exit_interface(g, px, front, cone.ex, cone.exact_n, None, materials)
        xi.var_geo = torch.zeros_like(px.alpha)
        merged = fp if subdivisions == 1 else gaussians(g, px.bi, sums.sum(1, keepdim=True))
        l_trans, variance = _rays_mixture(g, table, lighting, materials, options, px, front,
                                          cone, xi, merged, mode)
        reflected = None  # one lobe at the exact normal: the table's at the exit point
        apart = separation(fp) if subdivisions > 1 else None
        if apart is not None and bool((apart > 0).any()):
            # GSR where the footprint's normals form separate groups (facets): each
            # group's own lobe, widened as the poster does (flat facets: the front lobe
            # through each exit), blended in continuously
            lobes = _lobes(g, table, px, front, cone, fp, materials, options, mode,
                           exact=False, reflected=bounce)[0]
            covs, var_k = _paper_covariances(px, front.p_t1, cone, fp, lobes)
            l_k = _read(lighting, px, lobes, covs, options)
            l_trans = torch.lerp(l_trans, l_k, apart[:, None])
            variance = torch.lerp(variance, var_k, apart)
            sectors = _reflected(lobes)
            reflected = lambda e: torch.lerp(e, sectors, apart)  # noqa: E731
    l_refl = incident_radiance_sg(lighting, px.bi, px.p1, front.axis_r, front.k_r,
                                  options.env_lookup)
    passes = finish(g, table, lighting, materials, options, px, front, cone, xi, radiance,
                    l_refl, l_trans, torch.sqrt(variance.clamp(min=0.0)), reflected)
    return radiance.view(b, h, w, 3), passes


def _lobe_normals(fp: Footprint, cone: Cone, exact: bool, alpha_front: torch.Tensor,
                  lobes: int
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per pixel and subdivision: the weight (N, K), the proxy exit normal (N, K, 3) and the
    exit roughness of each roughness lobe with its weight (N, K, ``lobes``: one at the mean
    alpha^2, or the two-point match of :mod:`.moments`). As in ``rousiers``
    (:func:`..rousiers.cone.back_ndf`), a footprint of under four pixels trusts the exact
    exit normal more than pixel-sized texels (``exact``: always, the rays carry the
    geometry, as ``rousiers``' exact normal); where the exit or its moments are
    missing, one lobe at the exact normal with the front roughness."""
    k = fp.weight.shape[1]
    have = cone.ex.found & (fp.weight.sum(-1) > 0.5)
    one = torch.zeros_like(fp.weight)
    one[:, 0] = 1.0
    weight = torch.where(have[:, None], fp.weight, one)
    w_ndf = (torch.log2(cone.minor) / 2.0).clamp(0.0, 1.0)[:, None, None]
    if exact:
        w_ndf = torch.zeros_like(w_ndf)
    exact_n = cone.exact_n[:, None, :].expand(-1, k, -1)
    blended = normalize(w_ndf * fp.normal + (1.0 - w_ndf) * exact_n)
    use = have[:, None] & (fp.weight > 0)
    normals = torch.where(use[..., None], blended, exact_n)
    if lobes == 2:
        a2, aw = fp.alpha2, fp.alpha2_w
    else:
        a2, aw = 2.0 * fp.var_mu[..., None], torch.ones_like(fp.var_mu)[..., None]
    alphas = torch.where(use[..., None], torch.sqrt(a2.clamp(min=mf.ALPHA_MIN ** 2)),
                         alpha_front[:, None, None])
    aw = torch.where(use[..., None], aw, torch.full_like(aw, 1.0 / aw.shape[-1]))
    return weight, normals, alphas, aw


def _lobes(g: GBuffer, table, px: Pixels, front: FrontLobes, cone: Cone, fp: Footprint,
           materials: MaterialBatch, options, mode: str, exact: bool, reflected: bool):
    """The exit lobes of a footprint's Gaussians, one per subdivision and roughness node
    (the SG table's lobe for its normal and roughness under the exit rule ``mode``), with
    the subdivisions' weights (N, K) and normals (N, K, 3). Without a roughness map the two
    roughness nodes coincide: one lobe (the same image, half the lookups). ``reflected``:
    also what each lobe's interface reflects inside (for the bounces, :func:`_reflected`;
    zeros otherwise)."""
    lobes_r = options.roughness_lobes if materials.has_maps else 1
    weight, normals, alphas, alpha_w = _lobe_normals(fp, cone, exact, px.alpha, lobes_r)
    lobes = []
    for j in range(fp.weight.shape[1]):
        xi = exit_interface(g, px, front, cone.ex, normals[:, j], None, materials)
        xi.var_geo = torch.zeros_like(px.alpha)  # the table's lobe alone: widened later
        for r in range(alphas.shape[-1]):
            a = alphas[:, j, r]
            axis, k, energy = exit_lobe(table, px, xi, materials, "rays", mode, a)
            refl = spread_energies(table, xi.cos2, xi.var1, xi.eta, a, px.dist)[1] \
                if reflected else torch.zeros_like(a)
            lobes.append(_Lobe(xi, axis, k, energy, weight[:, j] * alpha_w[:, j, r], j, a,
                               refl))
    return lobes, normals, weight


def _read(lighting: Lighting, px: Pixels, lobes: list[_Lobe], covs, options) -> torch.Tensor:
    """The light the lobes read (N, 3): each by EWA taps, times its share and energy."""
    out = torch.zeros_like(px.p1)
    for lobe, (axis, cov, e1, e2) in zip(lobes, covs):
        out = out + (lobe.share * lobe.energy)[:, None] * ewa_radiance(
            lighting, px.bi, lobe.xi.p2, axis, cov, e1, e2, options.ewa_taps,
            options.env_lookup)
    return out


def _rays_mixture(g: GBuffer, table, lighting: Lighting, materials: MaterialBatch, options,
                  px: Pixels, front: FrontLobes, cone: Cone, xi: ExitInterface,
                  fp: Footprint, mode: str):
    """``spread: rays``: the light read by the lobes of a footprint's merged Gaussian (its
    roughness nodes, at the exact exit normal), each widened by the bounding rays'
    covariance (:func:`_ray_covariances`), and the mixture's per-axis variance."""
    lobes = _lobes(g, table, px, front, cone, fp, materials, options, mode, exact=True,
                   reflected=False)[0]
    covs, variance = _ray_covariances(g, px, front.p_t1, front.k_t1, cone, xi, lobes)
    return _read(lighting, px, lobes, covs, options), variance


def _reflected(lobes: list[_Lobe]) -> torch.Tensor:
    """What the lobes' interfaces reflect inside (N,), by their shares: with internal
    bounces the light the exit keeps matches the lobes' transmitted energies."""
    return sum(lb.share * lb.reflected for lb in lobes)


def _paper_covariances(px: Pixels, p_t1: torch.Tensor, cone: Cone, fp: Footprint,
                       lobes: list[_Lobe]):
    """``spread: paper``: each lobe's own NDF and the front lobe convolved through its exit
    (:func:`.lobes.paper_covariance`; the NDF's geometric part shrinks with a footprint
    under a pixel, as ``rousiers``' kappa_G). Returns per lobe (axis, covariance, e1, e2)
    and the mixture's per-axis variance (N,)."""
    out, variance = [], torch.zeros_like(px.alpha)
    sub2 = cone.sub.square()[:, None, None]
    found = cone.ex.found[:, None, None]
    for lobe in lobes:
        xi = lobe.xi
        cos_in = clamp_to_critical(xi.cos2, xi.tir, xi.cos_crit)
        cov, e1, e2 = paper_covariance(p_t1, xi.n_in, cos_in, px.ior, xi.var1,
                                       sub2 * fp.cov[:, lobe.j], fp.u[:, lobe.j],
                                       fp.v[:, lobe.j], lobe.axis)
        cov = torch.where(found, cov, torch.zeros_like(cov)) + _iso(_var(lobe.k), cov)
        out.append((lobe.axis, cov, normalize(e1), e2))
        variance = variance + lobe.share * 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    return out, variance


def _ray_covariances(g: GBuffer, px: Pixels, p_t1: torch.Tensor, k_t1: torch.Tensor,
                     cone: Cone, xi: ExitInterface, lobes: list[_Lobe]):
    """``spread: rays`` (ours): the bounding rays' exit directions give the covariance R of
    the front lobe carried through the object to the exit (:func:`.lobes.ray_covariance`:
    the geometry's part, the same for every lobe); each lobe (a roughness node of the
    merged Gaussian at the exact exit normal) keeps its own axis, the SG table's for its
    roughness, and is R plus its microfacet part wide: the convolution of the exit's BTDF
    lobe with the arriving light's spread (the poster's "convolve for the outgoing
    refraction lobe", per roughness lobe as de Rousiers' levels, sec. 5.1). The nodes'
    axes differ by the table's roughness-dependent shift, a microfacet effect that R does
    not contain, so their spread is kept, not traded against R. Returns per lobe (axis,
    covariance, e1, e2; the basis (e_perp x axis, e_perp), R's axes carried there) and the
    mixture's per-axis variance (N,)."""
    e2 = incidence_frame(p_t1, xi.n_in)[0]
    n4, ok4 = bounding_normals(g, cone, px.bi)
    rays, cnt = ray_covariance(p_t1, cone.exact_n, cone.dirs, n4, ok4, px.ior, e2)
    rays = torch.where((cnt > 0)[:, None, None], rays, _iso(xi.mag2 / k_t1, rays))
    within = psd2(rays)
    found = cone.ex.found
    out, variance = [], torch.zeros_like(px.alpha)
    if len(lobes) > 1:  # the nodes' axes about their mean (the mixture's own spread)
        mean = sum(lb.share[:, None] * lb.axis for lb in lobes)
        variance = 0.5 * sum(lb.share * dot(lb.axis - mean, lb.axis - mean) for lb in lobes)
    for lobe in lobes:
        axis = torch.where(found[:, None], normalize(lobe.axis), lobe.axis)
        e1 = normalize(torch.cross(e2, lobe.axis, dim=-1))
        cov = torch.where(found[:, None, None], within, torch.zeros_like(within)) \
            + _iso(_var(lobe.k), within)
        out.append((axis, cov, e1, e2))
        variance = variance + lobe.share * 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    return out, variance


def _iso(var: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(N, 2, 2) isotropic covariance of per-axis variance ``var`` (N,)."""
    return var[:, None, None] * torch.eye(2, dtype=like.dtype)


def _var(k: torch.Tensor) -> torch.Tensor:
    """Per-axis variance 1 / k of SG lobes of sharpness k."""
    return 1.0 / k.clamp(min=1e-12)


__all__ = ["render_lean"]
