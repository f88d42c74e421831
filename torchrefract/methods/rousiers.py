"""Method ``rousiers``: de Rousiers et al. 2012, Real-Time Rendering of Rough Refraction.

Per object pixel (all pixels of the batch at once, compacted):

1. Front interface: the SG fit of the Walter BTDF and BRDF (``sgfit``, eqs. 8-9) gives the
   transmitted lobe (energy E_t1, sharpness k_t1, axis p_t1) and the reflected lobe
   (E_r, k_r, p_r) for the view angle, the IOR and the local roughness.
2. Cone tracing (sec. 4.3): four rays at theta_b = acos(0.25^(1 / (k_t1 + 1))) (eq. 12)
   around p_t1 bound 75% of the lobe; they and the axis are marched through the back-face
   buffer (``march``). The screen positions of the four exits give the footprint.
3. Geometry filtering (sec. 4.2): the back-face NDF mip (Toksvig, ``ndf``) is read at the
   footprint's scale: the mip level comes from the footprint's minor extent and four taps
   spread along its major extent average the anisotropic part (a box-filtered stand-in for
   the paper's anisotropic ``textureGrad``). Its spread gives kappa_G (eq. 11), which is
   convolved with the exit roughness's Blinn-Phong exponent (eq. 10).
4. Exit interface: the mean back normal is the proxy surface; the SG table for leaving the
   glass (eta = 1 / ior) at the angle between p_t1 and that normal, with the convolved
   roughness, gives the exit lobe (E_t2, k_t2, p_t2).
5. The environment is read from the SG-pre-convolved pyramid (``sgenv``, sec. 4.1) around
   p_t2 with the lobe's sharpness; the front reflection likewise around p_r.

    L = E_r L_env(p_r, k_r) + E_t1 E_t2 exp(-sigma s) L_env(p_t2, k)

How wide the exit lobe is (``spread``). The paper (``paper``) assumes all rays reach the
exit parallel: the front lobe's own angular spread only enters through the NDF of the
footprint, convolved with the exit roughness as if it were roughness (eq. 10). That drops
the spread on a flat slab (the image would show only the exit roughness) and overstates it
on convex shapes: inside a ball lens a ray tilted by delta meets a normal tilted by
2 delta, so it leaves tilted by (2 - eta) delta, not sqrt(eta^2 + 4 (eta - 1)^2) delta.
``paper+front`` adds the front lobe's variance 1/k_t1 magnified by the exit refraction
(d theta_out / d theta_in = ior cos(theta_in) / cos(theta_out)). ``rays`` (default, ours)
measures the mapping directly: the four marched bounding rays are refracted out at their
own exit normals, and their angles to the central exit direction give the geometric part
of the lobe's variance, added to the exit roughness's lobe (which then uses the exact exit
normal, not the NDF). It costs nothing extra: the rays are marched anyway.

The exit rule (``tir``). ``conserve`` (default; ours): what the exit reflects inside (all
of it under total internal reflection) leaves there too, with the transmitted lobe (its
incident angle clamped to the critical angle), times the fraction of trapped light that
eventually escapes (:func:`torchrefract.shading.bounces.escape_fraction`), so the image is
continuous in roughness and IOR at the critical angle and a white furnace keeps what
Mitsuba keeps. Its energies (and the split's, with internal bounces) are averaged over the
front lobe arriving at the exit (:func:`torchrefract.optics.sgfit.spread_cosines`, variance
1/k_t1; at later bounces, the variance carried). ``clamp`` (the paper's and Wyman's choice): the incident angle is clamped to
the critical angle and all the transmitted light leaves with that lobe (weight 1, as
``specular`` does, so the smooth limit matches it), the exit's reflection outside TIR is
lost; ``tir: reflect`` reads the environment with the table's internal reflection lobe
instead.
Rays whose exit is not found fall back to the front lobe alone (direction p_t1).

``internal_bounces`` (K > 0 or ``auto``, :mod:`torchrefract.shading.bounces`; ours, beyond the
paper): at the exit the table's internal reflection lobe (E_ri, k_ri: leaving the glass, eta
= 1 / ior) carries E_ri of the light back inside; one ray stands for it, along the mirror
direction about the interface normal, and is marched to the next interface (front or back
layer), where the table again splits it into a transmitted lobe (read from the pyramid) and
a reflected one, K times. The ray is the lobe's mode, not the SG fit's axis: near the
critical angle the fitted axis swings off the mirror direction with roughness and angle
(alpha 0.3: 18 degrees at cos 0.8, 0 at 0.6, 12 at 0.4 inside IOR 1.5 glass), so a ray along
it crossed folds of the geometry as roughness changed (per-pixel flicker in a roughness
sweep) and, measured on the suite, landed worse on average (FLIP against 1024-spp truth at
64x64, mean over the 12 scenes, axis -> mirror: 2 bounces 0.153 -> 0.143, ``auto`` bounces
0.143 -> 0.129, 2 bounces with four rays 0.140 -> 0.135). A lobe's angular variance is
carried along: the front lobe's 1/k_t1, plus 1/k_r at each reflection (a reflection keeps
angular spread; the curvature of the reflecting surface is not modelled), magnified by the
exit refraction (d theta_out / d theta_in)^2 where it leaves. The ``tir`` rule applies at
the last interface only; under ``conserve`` a lobe that has grown wide is let out before
that, gradually: at each interface the fraction 1 - exp(-var / ``DIFFUSE_VAR``) of what it
reflects inside leaves there as at the last interface (the bounces not followed, summed in
closed form), the rest goes on as a ray. A bounce whose march finds no next interface (the
image-space march lost it) leaves along its own direction with the escape fraction of
trapped light (:func:`torchrefract.shading.bounces.escape_fraction`; 1 for smooth glass).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchrefract.geometry.camera import project
from torchrefract.geometry.gbuffer import GBuffer, interpolate
from torchrefract.kernels import native
from torchrefract.kernels.index import put_, take, where_true
from torchrefract.kernels.march import camera_coordinates, camera_planes, march_back
from torchrefract.lighting.lights import Lighting, incident_radiance_sg
from torchrefract.methods.base import Method, Shaded
from torchrefract.optics import microfacet as mf
from torchrefract.optics.exit_rule import TIR_RULES
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.ndf import (
    KAPPA_MAX,
    build_box_mips,
    build_ndf_mips,
    combine_exponents,
    kappa_from_length,
    sample_box_mips,
    sample_mips,
)
from torchrefract.optics.sgfit import (
    load_sg_table,
    lobe_axis,
    matched_fade,
    sg_energies,
    sg_lookup,
    spread_cosines,
    spread_mean,
)
from torchrefract.optics.smooth import dot, face_forward, normalize, reflect, refract, tangent_frame
from torchrefract.options import nested, option
from torchrefract.shading.background import background, light_in_front
from torchrefract.shading.bounces import (
    Arrival,
    BounceSettings,
    Shading,
    bounce_passes,
    escape_fraction,
    follow,
)

DIFFUSE_VAR = 0.2
"""Internal bounces under ``tir: conserve``: the angular variance (per axis, radians^2;
~26 degrees standard deviation) at which a reflected lobe is counted as diffuse. At each
interface a fraction 1 - exp(-var / DIFFUSE_VAR) of the light it reflects inside is no
longer followed as a ray but leaves there in closed form, as at the last interface
(``escape_fraction``; module docstring). Chosen on the suite (in-sample; 64x64 FLIP against
1024-spp truth, mean over the 12 scenes, ``auto`` / 2 bounces / 2 bounces with 4 rays):
not at all 0.129 / 0.143 / 0.135; 0.05: 0.140 / 0.145 / 0.144; 0.1: 0.131 / 0.138 / 0.140;
0.2: 0.125 / 0.135 / 0.137; 0.3: 0.123 / 0.135 / 0.136; 0.5: 0.123 / 0.136 / 0.136. The
suzanne roughness sweep's largest 1% pixel step with ``auto`` bounces: 0.177 without,
0.134 at 0.2, 0.145 at 0.3 (bound 0.15)."""


@dataclass(frozen=True)
class RousiersOptions:
    """Settings of ``rousiers`` (``method_options`` in a scene)."""

    tir: str = option("conserve", choices=TIR_RULES)
    """Exit rule (module docstring): ``conserve``, ``clamp`` (the paper's) or ``reflect``."""
    cone_rays: str = option("march", choices=("march", "plane"))
    """Footprint rays: ``march`` (the paper: march the four bounding rays) or ``plane``
    (intersect them with the exit point's tangent plane: 5x fewer march steps)."""
    spread: str = option("rays", choices=("paper", "paper+front", "rays"))
    """How the exit lobe gets its width beyond the exit roughness (module docstring):
    ``paper`` (footprint NDF convolved with the BTDF, eq. 10), ``paper+front`` (that, plus
    the front lobe's spread magnified by the exit refraction) or ``rays`` (the four marched
    bounding rays refracted at their own exit normals)."""
    march_steps: int = option(24, minimum=1, maximum=4096, integer=True)
    """Coarse samples of the central ray's march (fewer change nothing measurable on the
    suite: bisection refines the hit, then the exact triangle is intersected)."""
    cone_march_steps: int = option(4, minimum=1, maximum=4096, integer=True)
    """Coarse samples of each bounding ray's march (only the footprint and the lobe's
    spread need them; 4 and 8 give the same FLIP within 0.001 on the suite)."""
    refine_steps: int = option(8, minimum=0, maximum=64, integer=True)
    """Bisection iterations after the coarse search of the central ray and the internal
    bounces (fewer give the same FLIP on the suite, but lose more exits where the ray
    leaves near a silhouette: with 3, the 2-bounce roughness sweep on suzanne flickers
    more, 99th-percentile pixel step 0.218 against 0.191)."""
    cone_refine_steps: int = option(3, minimum=0, maximum=64, integer=True)
    """Bisection iterations of each bounding ray's march (the exit is then the exact hit
    with the triangle found there, walked to the one containing it: 3 and 8 give the same
    FLIP within 0.001 on the suite)."""
    roughness_levels: int = option(4, minimum=2, maximum=16, integer=True)
    """With a roughness map: how many roughness levels the exit interface is split into
    (coverage ratios, sec. 5.1)."""
    bounces: BounceSettings = nested(BounceSettings)
    """Internal reflections (keys ``internal_bounces``, ``bounce_tolerance``,
    ``max_internal_bounces``, ``bounce_march_steps``, ``bounce_rays``)."""


def bounding_angle(k: torch.Tensor) -> torch.Tensor:
    """theta_b = acos(0.25^(1 / (k + 1))), the cone holding 75% of an SG lobe (eq. 12).

    Computed as 2 asin(sqrt((1 - x) / 2)) with 1 - x = -expm1(-ln 4 / (k + 1)): the same
    angle, accurate and with a finite gradient for sharp lobes (acos' diverges at 1).
    """
    one_minus = -torch.expm1(-math.log(4.0) / (k + 1.0))
    return 2.0 * torch.asin(torch.sqrt(0.5 * one_minus))


def _lobe(table, cos_theta, eta, alpha, dist: torch.Tensor, lobe: str):
    """SG table lookup; GGX pixels use the L2-optimal sharpness.

    Moment matching (the paper's fit) is dominated by GGX's heavy tails: its peak comes out
    2-5x too low. The table also stores, for each entry, the sharpness minimizing the L2
    distance to the true lobe at the same energy and axis; Beckmann's two agree within a
    few percent, so Beckmann keeps the paper's moments.
    """
    out = sg_lookup(table, cos_theta, eta, alpha, dist, lobe, sharpness="moment")
    ggx = dist == 1
    if bool(ggx.any()):
        l2 = sg_lookup(table, cos_theta, eta, alpha, dist, lobe, sharpness="l2")
        out = tuple(torch.where(ggx, b, a) for a, b in zip(out, l2))
    fade = matched_fade(eta)
    if bool((fade < 1).any()):  # near IOR 1: the roughness's energy change fades out
        a, k, t, e = out
        e0 = sg_lookup(table, cos_theta, eta, torch.full_like(alpha, table.spec.alpha_min),
                       dist, lobe)[3]
        near = fade < 1  # elsewhere exactly the unfaded values (batch-independent bits)
        e_f = torch.where(near, e0 + fade * (e - e0), e)
        a = torch.where(near, a * e_f / e.clamp(min=1e-12), a)  # scales with the energy
        out = (a, k, t, e_f)
    return out


def _energies(table, cos_theta: torch.Tensor, var: torch.Tensor, eta: torch.Tensor,
              alpha: torch.Tensor, dist: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The transmitted and reflected lobes' energies (``_lobe``'s, faded the same way near
    IOR 1) averaged over a lobe of arriving directions of variance ``var`` around the axis
    at ``cos_theta`` (:func:`torchrefract.optics.sgfit.spread_cosines`), (N,) each."""
    cs = spread_cosines(cos_theta, var)  # (3, N)
    args = [x.expand_as(cs) for x in (eta, alpha, dist)]
    e_t, e_r = sg_energies(table, cs, *args)
    fade = matched_fade(eta)
    if bool((fade < 1).any()):
        e_t0, e_r0 = sg_energies(table, cs, args[0], torch.full_like(cs, table.spec.alpha_min),
                                 args[2])
        near = fade < 1  # elsewhere exactly the unfaded values (batch-independent bits)
        e_t = torch.where(near, e_t0 + fade * (e_t - e_t0), e_t)
        e_r = torch.where(near, e_r0 + fade * (e_r - e_r0), e_r)
    return spread_mean(e_t), spread_mean(e_r)


def _true_angle_transmit(table, e_t_clamped: torch.Tensor, tir: torch.Tensor,
                         cos_theta: torch.Tensor, eta: torch.Tensor, alpha: torch.Tensor,
                         dist: torch.Tensor) -> torch.Tensor:
    """The transmitted lobe's energy at the true incident angle ``cos_theta``, given
    ``e_t_clamped``, the lookup at that angle clamped to the critical one under ``tir``:
    the two agree elsewhere, so only the TIR points are looked up again."""
    sel = where_true(tir)
    if sel.numel() == 0:
        return e_t_clamped
    e = e_t_clamped.clone()
    put_(e, sel, _lobe(table, take(cos_theta, sel), take(eta, sel), take(alpha, sel),
                       take(dist, sel), "transmit")[3])
    return e


def _footprint(q: torch.Tensor, ok4: torch.Tensor, center: torch.Tensor, proj: torch.Tensor,
               bi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Screen footprint of the four bounding rays' exits q (N, 4, 3) (found: ok4 (N, 4)),
    with the central exit (N, 3) standing in for those not found; proj (B, 16) per view.

    Returns xy (N, 4, 2), the central exit's xy_c (N, 2) and the bounding box's extent
    (N, 2) in pixels (the native kernel where no gradient flows: the same values)."""
    if native.no_grad_through(q, center):
        res = native.footprint(q, ok4, center, proj, bi)
        if res is not None:
            return res
    pr = take(proj, bi)
    xy, _ = project(q, pr)  # (N, 4, 2)
    xy_c, _ = project(center[:, None, :], pr)
    xy_c = xy_c[:, 0]
    xy = torch.where(ok4[..., None], xy, xy_c[:, None, :])
    return xy, xy_c, xy.max(1).values - xy.min(1).values


def _ray_spread(p_t1: torch.Tensor, exact_n: torch.Tensor, dirs: torch.Tensor,
                n4: torch.Tensor, ok4: torch.Tensor, ior: torch.Tensor,
                fallback: torch.Tensor) -> torch.Tensor:
    """The geometric part of the exit lobe's per-axis variance (N,) (``spread: rays``): the
    bounding rays dirs (N, 4, 3) refracted out at their exit normals n4 (found: ok4), and
    their squared angles to the central ray p_t1 refracted out at exact_n; ``fallback``
    where none found its exit (the native kernel where no gradient flows: the same
    values)."""
    if native.no_grad_through(p_t1, exact_n, dirs, n4, ior, fallback):
        res = native.spread(p_t1, exact_n, dirs, n4, ok4, ior, fallback)
        if res is not None:
            return res
    t_c, _ = refract(p_t1, face_forward(-exact_n, p_t1), ior)
    t_k, _ = refract(dirs, face_forward(-n4, dirs), ior[:, None])
    # squared chord |t_k - t_c|^2 = 2 (1 - cos a) ~ a^2: smooth (acos' diverges at 0)
    dk = t_k - t_c[:, None, :]
    chord2 = dot(dk, dk)
    ang2 = torch.where(ok4, chord2, torch.zeros_like(chord2))
    cnt = ok4.sum(-1)
    var_geo = ang2.sum(-1) / cnt.clamp(min=1) / (2.0 * math.log(4.0))
    return torch.where(cnt > 0, var_geo, fallback)


def _level_values(materials: MaterialBatch, n: int) -> torch.Tensor:
    """(B, n) roughness levels spanning each scene's roughness_range (or its uniform value)."""
    t = torch.linspace(0.0, 1.0, n)
    lo, hi = materials.roughness_range.unbind(-1)  # (B,)
    vals = lo[:, None] + t[None, :] * (hi - lo)[:, None]
    uniform = torch.tensor([m is None for m in materials.roughness_maps])
    return torch.where(uniform[:, None], materials.roughness[:, None].expand_as(vals), vals)


def _level_coverage(g: GBuffer, materials: MaterialBatch, n: int) -> torch.Tensor:
    """(B, H, W, n) per back-layer pixel: its roughness as hat weights on the n levels
    (linear between the two nearest), zero where the back layer is empty."""
    b, h, w = g.shape
    flat_b = torch.arange(b).repeat_interleave(h * w)
    alpha = materials.roughness_at(flat_b, g.back.uv.reshape(-1, 2))  # (B*H*W,)
    lo, hi = materials.roughness_range[flat_b].unbind(-1)
    pos = ((alpha - lo) / (hi - lo).clamp(min=1e-12)).clamp(0.0, 1.0) * (n - 1)
    idx = torch.arange(n, dtype=pos.dtype)
    wts = (1.0 - (pos[:, None] - idx[None, :]).abs()).clamp(min=0.0)  # (B*H*W, n)
    wts = wts * g.back.mask.reshape(-1, 1).to(wts.dtype)
    return wts.view(b, h, w, n)


def render_rousiers(g: GBuffer, lighting: Lighting, materials: MaterialBatch,
                    options: RousiersOptions = RousiersOptions()
                    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Shade a G-buffer with de Rousiers' rough refraction (see the module docstring).

    Args:
        g: G-buffer of B views at (H, W) (sub-)pixels.
        lighting: environment maps (SG pyramids built once per file) and lights.
        materials: IOR, roughness, distribution and absorption per scene.
        options: method settings.

    Returns:
        radiance: (B, H, W, 3) float32, background included.
        passes: ``exit_found``, ``tir`` (0/1), ``lobe_sigma`` (per-axis angular spread of
            the final transmitted lobe, radians), ``footprint`` (pixels, major extent).
    """
    b, h, w = g.shape
    radiance = background(g, lighting)
    hw = h * w
    idx = g.front.mask.reshape(-1).nonzero(as_tuple=True)[0]
    passes = {k: torch.zeros(b * hw) for k in ("exit_found", "tir", "lobe_sigma", "footprint")}
    if idx.numel() == 0:
        out = {k: v.view(b, h, w, 1) for k, v in passes.items()}
        if options.bounces.enabled:  # the same passes as a batch with object pixels
            out.update(bounce_passes(g, idx, None))
        return radiance.view(b, h, w, 3), out
    table = load_sg_table()
    bi = idx // hw
    d = take(g.ray_dir.reshape(-1, 3), idx)  # (N, 3)
    p1 = take(g.front.position.reshape(-1, 3), idx)
    n1 = face_forward(take(g.front.normal.reshape(-1, 3), idx), d)  # view side
    ior = take(materials.ior, bi)
    # Front roughness: the map at the front hit's UV (sec. 5.1), else the uniform value.
    alpha = materials.roughness_at(bi, take(g.front.uv.reshape(-1, 2), idx)
                                   ).clamp(min=mf.ALPHA_MIN)
    dist_b = materials.distribution_index()
    dist = take(dist_b, bi)
    view = -d
    cos1 = dot(view, n1).clamp(0.0, 1.0)

    # 1. Front interface lobes (eqs. 8-9).
    _, k_r, t_r, e_r = _lobe(table, cos1, ior, alpha, dist, "reflect")
    axis_r = lobe_axis(view, n1, t_r, "reflect")
    _, k_t1, t_t1, e_t1 = _lobe(table, cos1, ior, alpha, dist, "transmit")
    p_t1 = normalize(lobe_axis(view, n1, t_t1, "transmit"))

    # 2. Cone tracing: the axis and four bounding rays (eq. 12).
    planes = camera_planes(g)  # built once for the axis and the bounding rays
    c_p1, c_t1 = camera_coordinates(g, bi, p1, p_t1)
    ex = march_back(g, bi, p1, p_t1, steps=options.march_steps, refine=options.refine_steps,
                    planes=planes, camera=(c_p1, c_t1))
    theta_b = bounding_angle(k_t1)[:, None]
    u, v = tangent_frame(p_t1)
    cos_b, sin_b = torch.cos(theta_b), torch.sin(theta_b)
    dirs = torch.stack([cos_b * p_t1 + sin_b * s * a
                        for a in (u, v) for s in (1.0, -1.0)], 1)  # (N, 4, 3)
    n = idx.numel()
    if options.cone_rays == "march":
        # The bounding rays start at p1 with directions combining p_t1, u and v: their
        # camera coordinates combine those of the axis (no per-ray camera transform).
        _, c_u = camera_coordinates(g, bi, p1, u)
        _, c_v = camera_coordinates(g, bi, p1, v)
        cb, sb = cos_b.detach(), sin_b.detach()
        c_dirs = torch.stack([cb * c_t1 + sb * s * c for c in (c_u, c_v)
                              for s in (1.0, -1.0)], 1)  # (N, 4, 3)
        ex4 = march_back(g, bi.repeat_interleave(4), p1.repeat_interleave(4, 0),
                         dirs.reshape(-1, 3), steps=options.cone_march_steps,
                         refine=options.cone_refine_steps, planes=planes,
                         camera=(c_p1.repeat_interleave(4, 0), c_dirs.reshape(-1, 3)))
        q = ex4.position.view(n, 4, 3)
        ok4 = ex4.found.view(n, 4)
        n4 = ex4.normal.view(n, 4, 3)
    else:  # intersect with the tangent plane at the central exit
        pn = torch.where(ex.found[:, None], ex.normal, p_t1)
        denom = dot(dirs, pn[:, None, :])
        s = dot(ex.position - p1, pn)[..., None] / denom.clamp(min=1e-6)
        q = p1[:, None, :] + s[..., None] * dirs
        ok4 = (denom > 1e-6) & ex.found[:, None]
        n4 = None  # read from the back layer below, at the exits' pixels
    # Footprint in pixels: screen bounding box of the four exits.
    xy, xy_c, ext_raw = _footprint(q, ok4, ex.position, g.proj, bi)
    ext = ext_raw.clamp(min=1.0)
    major = ext.max(-1).values
    minor = ext.min(-1).values
    level = torch.log2(minor)
    # A footprint smaller than a pixel sees less of the surface than the finest NDF texel:
    # its normal spread shrinks with its area (variance ~ extent^2), down to the exact exit
    # normal of a specular ray. Without this a smooth object would be blurred by the
    # pixel grid itself.
    sub = ext_raw.min(-1).values.clamp(0.0, 1.0)  # (N,) 1 once the footprint spans a pixel
    exact_n = torch.where(ex.found[:, None], ex.normal, p_t1)
    kappa_g = None
    if options.spread == "rays":
        # The geometry's part of the lobe comes from the bounding rays (below), at the exact
        # exit normal: the footprint's NDF is not needed.
        n_bar = exact_n
    else:
        # 3. NDF of the back layer over the footprint: 4 taps along the major axis.
        mips = build_ndf_mips(g.back.normal, g.back.mask, g.back.depth)
        along_x = (ext[:, 0] >= ext[:, 1])[:, None]
        offsets = torch.tensor([-0.375, -0.125, 0.125, 0.375])
        vec = torch.zeros(n, 3)
        cov = torch.zeros(n)
        for o in offsets:
            shift = torch.where(along_x, torch.stack([o * major, torch.zeros_like(major)], -1),
                                torch.stack([torch.zeros_like(major), o * major], -1))
            nd, nl, nc = sample_mips(mips, bi, xy_c + shift, level)
            vec = vec + nd * (nl * nc)[:, None]
            cov = cov + nc
        mean = vec / cov.clamp(min=1e-12)[:, None]
        length = mean.norm(dim=-1)
        have_ndf = ex.found & (cov > 1e-6) & (length > 1e-6)
        ndf_n = mean / length.clamp(min=1e-12)[:, None]
        # Proxy direction: over a footprint of a few pixels the exact exit normal (its
        # center) is a better estimate of the mean normal than bilinear taps of pixel-sized
        # texels (the footprint is symmetric, so curvature changes the mean only to second
        # order); from 4 pixels on, the mip's mean over the footprint takes over.
        w_ndf = (torch.log2(minor) / 2.0).clamp(0.0, 1.0)[:, None]
        n_bar = torch.where(have_ndf[:, None],
                            normalize(w_ndf * ndf_n + (1.0 - w_ndf) * exact_n), exact_n)
        kappa_g = torch.where(have_ndf,
                              kappa_from_length(length) / (sub * sub).clamp(min=1e-12),
                              torch.full_like(length, KAPPA_MAX)).clamp(max=KAPPA_MAX)

    # 4. Exit interface: view side is inside (looking back along p_t1).
    n_in = face_forward(-n_bar, p_t1)  # inward, facing against p_t1
    view2 = -p_t1
    cos2 = dot(view2, n_in).clamp(0.0, 1.0)
    cos_crit = torch.sqrt((1.0 - 1.0 / (ior * ior)).clamp(min=0.0))
    tir = (cos2 < cos_crit) & ex.found
    sin2 = (1.0 - cos2 * cos2).clamp(min=0.0)
    cos_out = torch.sqrt((1.0 - ior * ior * sin2).clamp(min=1e-4))
    mag2 = (ior * cos2 / cos_out) ** 2  # (d theta_out / d theta_in)^2 at the exit
    var_geo = None
    if options.spread == "rays":
        # The bounding rays (75% of the front lobe, eq. 12) refracted out at their own exit
        # normals: their angles to the central exit direction measure how the front lobe
        # maps through the object (a flat slab magnifies it by the exit refraction, a ball
        # lens focuses it). For an SG, 1 - exp(-k (1 - cos theta_b)) = 0.75 gives
        # theta_b^2 ~ 2 ln 4 / k, so a ray leaving at angle a adds a^2 / (2 ln 4) to the
        # per-axis variance 1/k.
        if n4 is None:
            flat = bi[:, None] * hw + (xy[..., 1].floor().clamp(0, h - 1).long() * w
                                        + xy[..., 0].floor().clamp(0, w - 1).long())
            n4 = take(g.back.normal.reshape(-1, 3), flat.reshape(-1)).view(n, 4, 3)
            ok4 = ok4 & take(g.back.mask.reshape(-1), flat.reshape(-1)).view(n, 4)
        # No bounding ray found its exit: fall back to the front lobe's magnified spread.
        var_geo = _ray_spread(p_t1, exact_n, dirs, n4, ok4, ior, mag2 / k_t1)
    p2 = torch.where(ex.found[:, None], ex.position, p1)
    path = torch.where(ex.found, ex.dist,
                       take((g.back.dist - g.front.dist).reshape(-1), idx).clamp(min=0.0))
    att = torch.exp(-take(materials.absorption, bi) * path[:, None])

    var1 = 1.0 / k_t1.clamp(min=1e-12)  # the front lobe's spread, arriving at the exit
    bounce = options.bounces.enabled
    # With internal bounces the first exit is not the last interface: the table's own split
    # between the transmitted and the internally reflected lobe applies (no TIR rule).
    exit_mode = "split" if bounce else options.tir

    def exit_lobe(alpha_exit: torch.Tensor):
        """Direction, sharpness and weight of the light leaving through an exit interface
        of roughness ``alpha_exit`` (N,)."""
        if options.spread == "rays":
            alpha2 = alpha_exit
        else:  # eq. 10: the footprint's NDF convolved with the BTDF's
            kappa_d = mf.blinn_phong_from_alpha(alpha_exit).clamp(min=0.0)
            alpha2 = mf.alpha_from_blinn_phong(combine_exponents(kappa_g, kappa_d))
        if exit_mode == "split":  # the energy averaged over the arriving lobe
            _, k_t2, t_t2, _ = _lobe(table, cos2, 1.0 / ior, alpha2, dist, "transmit")
            p_t2 = normalize(lobe_axis(view2, n_in, t_t2, "transmit"))
            weight2 = _energies(table, cos2, var1, 1.0 / ior, alpha2, dist)[0]
        elif exit_mode == "clamp":
            cos2_eff = torch.where(tir, cos_crit + 1e-4, cos2)
            _, k_t2, t_t2, e_t2 = _lobe(table, cos2_eff, 1.0 / ior, alpha2, dist, "transmit")
            p_t2 = normalize(lobe_axis(view2, n_in, t_t2, "transmit"))
            weight2 = torch.where(tir, torch.ones_like(e_t2), e_t2)
        elif exit_mode == "conserve":
            # The paper's clamp, made continuous: what the exit reflects inside (all of it
            # under TIR) leaves here too, with the transmitted lobe (clamped at the critical
            # angle), after the losses of the bounces it would take on its way out
            # (bounces.escape_fraction); the transmitted part is taken at the true angle.
            cos2_eff = torch.where(tir, cos_crit + 1e-4, cos2)
            _, k_t2, t_t2, e_t2 = _lobe(table, cos2_eff, 1.0 / ior, alpha2, dist, "transmit")
            p_t2 = normalize(lobe_axis(view2, n_in, t_t2, "transmit"))
            # Both energies at the true angles of the arriving lobe (``_energies``).
            esc = escape_fraction(table, materials.ior, dist_b, alpha_exit, bi)
            e_t2, e_r2 = _energies(table, cos2, var1, 1.0 / ior, alpha2, dist)
            weight2 = (e_t2 + e_r2 * esc).clamp(max=1.0)
        else:
            _, k_t2, t_t2, e_t2 = _lobe(table, cos2, 1.0 / ior, alpha2, dist, "transmit")
            _, k_ti, t_ti, e_ti = _lobe(table, cos2, 1.0 / ior, alpha2, dist, "reflect")
            p_t2 = normalize(lobe_axis(view2, n_in, t_t2, "transmit"))
            p_ti = normalize(lobe_axis(view2, n_in, t_ti, "reflect"))
            p_t2 = torch.where(tir[:, None], p_ti, p_t2)
            k_t2 = torch.where(tir, k_ti, k_t2)
            weight2 = torch.where(tir, e_ti, e_t2)
        if options.spread == "paper+front":  # front spread carried through the exit
            k = 1.0 / (1.0 / k_t2 + mag2 / k_t1)
        elif options.spread == "rays":
            k = 1.0 / (1.0 / k_t2 + var_geo).clamp(min=1e-12)
        else:
            k = k_t2
        # Fallback where the exit is not found: leave with the front lobe.
        p_out = torch.where(ex.found[:, None], p_t2, p_t1)
        k = torch.where(ex.found, k, k_t1)
        weight2 = torch.where(ex.found, weight2, torch.ones_like(weight2))
        return p_out, k, weight2

    # 5. Pre-convolved environment lookups.
    l_refl = incident_radiance_sg(lighting, bi, p1, axis_r, k_r)
    if not materials.has_maps:
        p_out, k, weight2 = exit_lobe(alpha)
        l_trans = incident_radiance_sg(lighting, bi, p2, p_out, k) * weight2[:, None]
    else:
        # Spatially varying roughness at the exit (sec. 5.1): coverage ratios of a few
        # roughness levels, carried through the mips like the NDF and read at the same
        # footprint; one exit lobe per level, summed with those ratios.
        cover = _level_coverage(g, materials, options.roughness_levels)  # (B, H, W, L)
        levels = _level_values(materials, options.roughness_levels)  # (B, L)
        c = sample_box_mips(build_box_mips(cover), bi, xy_c, level)  # (N, L)
        c = c / c.sum(-1, keepdim=True).clamp(min=1e-12)
        no_cov = c.sum(-1) < 0.5  # nothing covered: use the front roughness
        l_trans = torch.zeros_like(p1)
        k = torch.zeros_like(alpha)
        weight2 = torch.zeros_like(alpha)
        for li in range(levels.shape[1]):
            a_l = torch.where(no_cov, alpha, levels[bi, li].clamp(min=mf.ALPHA_MIN))
            w_l = torch.where(no_cov, torch.full_like(alpha, 1.0 / levels.shape[1]), c[:, li])
            p_l, k_l, wt_l = exit_lobe(a_l)
            l_trans = l_trans + (w_l * wt_l)[:, None] * incident_radiance_sg(
                lighting, bi, p2, p_l, k_l)
            k = k + w_l / k_l.clamp(min=1e-12)  # coverage-weighted variance (for the pass)
            weight2 = weight2 + w_l * wt_l
        k = 1.0 / k.clamp(min=1e-12)
    # An index-matched object (IOR exactly 1) has no interface at all: it is invisible.
    # (The microfacet model would still lose the masking-shadowing energy there.)
    matched = ior == 1.0
    e_r = torch.where(matched, torch.zeros_like(e_r), e_r)
    e_t = torch.where(matched, torch.ones_like(e_t1), e_t1)
    if bool(matched.any()):  # looked up only where some scene has IOR 1
        sel = where_true(matched)
        plain = incident_radiance_sg(lighting, take(bi, sel), take(p1, sel), take(d, sel),
                                     torch.full((sel.numel(),), float("inf")))
        l_trans = put_(l_trans.clone(), sel, plain)
    if bounce:
        # The light the exit reflects back inside, followed bounce by bounce. The exit's
        # internal reflection lobe uses the roughness at the exit point.
        n_pix = idx.numel()
        uv_x = interpolate(ex.bary, take(g.meshes.tri_uvs, ex.tri.clamp(min=0)))
        alpha_x = torch.where(ex.found, materials.roughness_at(bi, uv_x), alpha)
        a_x = alpha_x.clamp(min=mf.ALPHA_MIN)
        _, k_ri, _, _ = _lobe(table, cos2, 1.0 / ior, a_x, dist, "reflect")
        e_ri = _energies(table, cos2, var1, 1.0 / ior, a_x, dist)[1]
        p_ri = normalize(reflect(p_t1, n_in))  # the lobe's ray: mirror (docstring)
        w1 = e_t1[:, None] * att
        first = Shading(radiance=w1 * l_trans, direction=p_ri,
                        reflectance=torch.where(ex.found & ~matched, e_ri,
                                                torch.zeros_like(e_ri)),
                        var=1.0 / k_t1.clamp(min=1e-12) + 1.0 / k_ri.clamp(min=1e-12))
        arrive = Arrival(pix=torch.arange(n_pix), batch=bi, p=p2, t=p_t1, normal=ex.normal,
                         uv=uv_x, found=ex.found, w=w1, var=1.0 / k_t1.clamp(min=1e-12))
        shade = _interface(table, lighting, materials, options.tir, first)
        res = follow(g, arrive, shade, materials.absorption, options.bounces, n_pix,
                     options.refine_steps)
        l_through = torch.where(matched[:, None], att * l_trans, res.radiance)
        l_obj = e_r[:, None] * l_refl + l_through
    else:
        l_obj = e_r[:, None] * l_refl + e_t[:, None] * att * l_trans
    hidden = light_in_front(lighting, bi, take(g.eye, bi), d,
                            take(g.front.dist.reshape(-1), idx))
    put_(radiance, idx, torch.where(hidden[:, None], take(radiance, idx),
                                    l_obj.to(radiance.dtype)))
    put_(passes["exit_found"], idx, ex.found.float())
    put_(passes["tir"], idx, tir.float())
    put_(passes["lobe_sigma"], idx, torch.rsqrt(k.clamp(min=1e-12)).float())
    put_(passes["footprint"], idx,
         torch.where(ex.found, major, torch.zeros_like(major)).float())
    out = {k: v.view(b, h, w, 1) for k, v in passes.items()}
    if bounce:
        out.update(bounce_passes(g, idx, res))
    return radiance.view(b, h, w, 3), out


def _interface(table, lighting: Lighting, materials: MaterialBatch, tir_mode: str,
               first: Shading):
    """The rough interface seen from inside (internal bounces; module docstring): the
    table's transmitted lobe leaves, its reflected lobe goes on. ``first``: the shading of
    the first exit, computed by the cone-traced path above."""
    dist_b = materials.distribution_index()

    def shade(a: Arrival, k: int, last: bool) -> Shading:
        if k == 0:
            return first
        bi = a.batch
        ior = take(materials.ior, bi)
        dist = take(dist_b, bi)
        alpha = materials.roughness_at(bi, a.uv).clamp(min=mf.ALPHA_MIN)
        n_view = face_forward(a.normal, a.t)  # inside, facing the arriving ray
        view = -a.t
        cos = dot(view, n_view).clamp(0.0, 1.0)
        cos_crit = torch.sqrt((1.0 - 1.0 / (ior * ior)).clamp(min=0.0))
        tir = cos < cos_crit
        one = torch.ones_like(cos)
        # the light leaving under TIR (the last interface's rule; under ``conserve`` the
        # diffuse part at every interface) leaves at the critical angle
        cos_t = torch.where(tir, cos_crit + 1e-4, cos) \
            if (last and tir_mode == "clamp") or tir_mode == "conserve" else cos
        _, k_t, t_t, e_t = _lobe(table, cos_t, 1.0 / ior, alpha, dist, "transmit")
        # The reflected lobe goes on (its spread), except at ``conserve``'s last interface,
        # where all of it leaves with the transmitted lobe: not looked up there.
        goes_on = not (last and tir_mode == "conserve")
        if goes_on:
            _, k_r, t_r, e_r = _lobe(table, cos, 1.0 / ior, alpha, dist, "reflect")
        else:
            k_r = torch.full_like(k_t, float("inf"))  # var unchanged: nothing follows it
        if not last or tir_mode == "conserve":  # the split: averaged over the lobe carried
            e_t, e_r = _energies(table, cos, a.var, 1.0 / ior, alpha, dist)
        p_t = normalize(lobe_axis(view, n_view, t_t, "transmit"))
        sin2 = (1.0 - cos_t * cos_t).clamp(min=0.0)
        mag2 = (ior * cos_t / torch.sqrt((1.0 - ior * ior * sin2).clamp(min=1e-4))) ** 2
        # The small-angle magnification diverges at the critical angle (cos_out -> 0) and
        # would turn a lobe near grazing exit into a uniform blur; a lobe cannot spread past
        # the hemisphere, so it is bounded at 2x (a heuristic: measured on the suite,
        # unbounded gave FLIP 0.259 at 2 bounces on the alpha-0.3 sphere, bounded 0.176).
        mag2 = mag2.clamp(max=4.0)
        k_out = 1.0 / (1.0 / k_t.clamp(min=1e-12) + mag2 * a.var)
        # The fraction of trapped light that eventually leaves (escape_fraction), looked up
        # once where ``conserve`` (its last interface, the diffuse part at every other) or a
        # lost ray needs it.
        lost_any = bool((~a.found).any())
        esc = escape_fraction(table, materials.ior, dist_b, alpha, bi) \
            if lost_any or tir_mode == "conserve" else None
        w_out, refl = e_t, e_r
        if tir_mode == "conserve":
            # What this interface reflects inside leaves here too, in closed form, after the
            # losses of the bounces not followed (escape_fraction): all of it at the last
            # interface, elsewhere the reflected lobe's diffuse part (DIFFUSE_VAR: a single
            # ray cannot stand for a lobe that wide, and following it through a non-convex
            # shape is chaotic, per-pixel flicker as roughness changes). It leaves with the
            # transmitted lobe (at the critical angle under TIR, ``cos_t``).
            go_on = torch.zeros_like(e_r) if last else \
                torch.exp(-(a.var + 1.0 / k_r.clamp(min=1e-12)) / DIFFUSE_VAR)
            w_out = (e_t + (1.0 - go_on) * e_r * esc).clamp(max=1.0)
            refl = go_on * e_r
        elif last:
            refl_part = e_r
            if tir_mode == "clamp":  # TIR light leaves at the critical angle: all that
                # this interface keeps at the true angle (the model loses some to masking)
                e_keep = (_true_angle_transmit(table, e_t, tir, cos, 1.0 / ior, alpha, dist)
                          + e_r).clamp(max=1.0)
                w_out = torch.where(tir, e_keep, e_t)
                refl_part = torch.where(tir, torch.zeros_like(e_r), e_r)
            else:  # reflect: under TIR the internal reflection lobe is read instead
                p_r = normalize(lobe_axis(view, n_view, t_r, "reflect"))
                p_t = torch.where(tir[:, None], p_r, p_t)
                k_out = torch.where(tir, 1.0 / (1.0 / k_r.clamp(min=1e-12) + a.var), k_out)
                w_out = torch.where(tir, e_r, e_t)
                refl_part = torch.where(tir, torch.zeros_like(e_r), e_r)
            refl = refl_part  # not followed: recorded as residual by the loop
        # Lost rays (the march found no next interface) leave along their current
        # direction with the lobe they carry, and with what light trapped inside eventually
        # lets out (escape_fraction: 1 for smooth glass; a found ray's last interface keeps
        # that too under conserve, so losing or finding the interface changes less).
        p_t = torch.where(a.found[:, None], p_t, a.t)
        k_out = torch.where(a.found, k_out, 1.0 / a.var.clamp(min=1e-12))
        w_out = torch.where(a.found, w_out, esc if lost_any else one)
        refl = torch.where(a.found, refl, torch.zeros_like(refl))
        l_out = incident_radiance_sg(lighting, bi, a.p, p_t, k_out)
        # the reflected lobe goes on along the mirror direction (module docstring)
        p_next = normalize(reflect(a.t, n_view))
        return Shading(radiance=a.w * w_out[:, None] * l_out, direction=p_next,
                       reflectance=refl,
                       var=a.var + 1.0 / k_r.clamp(min=1e-12))

    return shade


class Rousiers(Method):
    """de Rousiers et al. 2012, rough refraction by cone tracing (module docstring)."""

    name = "rousiers"
    Options = RousiersOptions

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        return Shaded(*render_rousiers(g, lighting, materials, options))


METHOD = Rousiers()

__all__ = ["METHOD", "RousiersOptions", "bounding_angle", "render_rousiers"]
