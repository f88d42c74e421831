"""Method ``specular``: two-sided image-space refraction (Wyman 2005), done exactly.

Per covered pixel: refract the camera ray at the front hit (Snell, shading normal), march the
refracted ray through the back-face buffer to its exit (Oliveira and Brauwers 2007; exact
triangle hit, see :mod:`torchrefract.kernels.march`), refract again with the IOR ratio inverted, and
look the environment up. The front surface's Fresnel reflection is added:

    L = F1 L_env(reflect(d)) + (1 - F1) W2 exp(-sigma s) L_env(T2)

with exact unpolarized dielectric Fresnel terms F1 (entry) and F2 (exit), s the path length
inside and sigma the absorption. The exit weight W2 is the ``tir`` rule's:

- ``conserve`` (default; ours): W2 = (1 - F2) + F2 P_esc. What the exit reflects inside
  (all of it under total internal reflection) leaves there too, along the refracted
  (critical-angle) direction, times the fraction of trapped light that eventually escapes
  (:func:`torchrefract.shading.bounces.escape_fraction`: 1 for smooth glass, below 1 for rough
  glass, which loses light to masking at every bounce). The image is continuous at the
  critical angle and smooth glass keeps its energy (the white furnace).
- ``clamp`` (Wyman's and de Rousiers' choice): W2 = 1 - F2, and under TIR the light leaves
  along the critical-angle direction with weight 1 (rough glass: what the interface keeps,
  less its masking loss), standing in for the light that escapes after further bounces;
  the exit's reflection outside TIR is lost.
- ``reflect``: under TIR the light is reflected once and the environment looked up in that
  direction.

Rough glass: the rays follow the smooth surface (no blur: see ``prefiltered`` and
``rousiers``), but the interfaces' energies are the rough surface's
(:func:`torchrefract.optics.sgfit.interface_energies`: F1, 1 - F1, F2, 1 - F2 become the Walter
BSDF's reflected and transmitted energies, which add up to less than 1), so the object has
the brightness of rough glass. The light reaching the exit is the entry's rough transmitted
lobe, not the one ray: under ``tir: conserve`` and with internal bounces, the exit's
energies are averaged over that lobe (:func:`torchrefract.optics.sgfit.spread_cosines`, around the
lobe's axis, which tilts towards grazing: ``_spread_exit``), and each internal reflection
adds its lobe's spread to the next interface's average; the papers' ``clamp`` and
``reflect`` keep the one ray's. Rays whose exit is not found (they leave the frame, miss the
back layer) fall back to the refracted direction T1, never to garbage.

``internal_bounces`` (K > 0 or ``auto``, :mod:`torchrefract.shading.bounces`): the exit interface
reflects F2 of the light back inside (all of it under TIR); that part is marched to the next
interface, where (1 - F) leaves along the refracted ray and F is reflected again, K times;
the ``tir`` rule then applies at the last interface.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from torchrefract.checks import check_choice, check_number, check_option_keys
from torchrefract.geometry.gbuffer import GBuffer, interpolate
from torchrefract.kernels.index import put_, take, where_true
from torchrefract.kernels.march import march_back
from torchrefract.lighting.lights import Lighting, hit_lights, incident_radiance
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.sgfit import (
    interface_energies,
    load_sg_table,
    sg_lookup,
    spread_interface_energies,
)
from torchrefract.optics.smooth import dot, face_forward, fresnel_dielectric, reflect, refract
from torchrefract.shading.bounces import Arrival, BounceSettings, Shading, escape_fraction, follow


@dataclass(frozen=True)
class SpecularOptions:
    """Settings of ``specular`` (``method_options`` in a scene)."""

    tir: str = "conserve"
    """Exit rule (module docstring): ``conserve``, ``clamp`` (the papers') or ``reflect``."""
    march_steps: int = 64
    """Coarse samples along the refracted ray (over the bounding sphere's chord)."""
    refine_steps: int = 10
    """Bisection iterations after the coarse search."""
    bounces: BounceSettings = BounceSettings()
    """Internal reflections (keys ``internal_bounces``, ``bounce_tolerance``,
    ``max_internal_bounces``, ``bounce_march_steps``)."""

    METHOD = "specular"
    BOUNCES = True  # whether the method follows internal reflections

    @classmethod
    def from_dict(cls, d: dict, source: str | None = None) -> "SpecularOptions":
        keys = [f.name for f in fields(cls) if f.name != "bounces"]
        if cls.BOUNCES:  # its lobes are rays: nothing for ``bounce_rays`` to split
            keys += [k for k in BounceSettings.FIELDS if k != "bounce_rays"]
        check_option_keys(d, keys, cls.METHOD, source)
        return cls(
            bounces=BounceSettings.from_dict(d, source),
            tir=check_choice(d.get("tir", "conserve"), "method_options.tir",
                             ("clamp", "reflect", "conserve"), source),
            march_steps=check_number(d.get("march_steps", 64), "method_options.march_steps",
                                     source, minimum=1, maximum=4096, integer=True),
            refine_steps=check_number(d.get("refine_steps", 10),
                                      "method_options.refine_steps", source, minimum=0,
                                      maximum=64, integer=True),
        )


@dataclass(frozen=True)
class Paths:
    """One refracted path per object pixel (compacted to the N covered (sub-)pixels).

    Attributes:
        idx: (N,) flat index into (B*H*W) of each object pixel; batch: (N,) its view.
        d: (N, 3) camera ray; p1: (N, 3) entry point; n1: (N, 3) entry normal facing the eye.
        f1: (N,) reflectance at entry (Fresnel; the rough surface's reflected energy);
        e1: (N,) transmittance at entry (1 - F; less the rough surface's masking loss).
        refl: (N, 3) mirror direction.
        t1: (N, 3) refracted direction inside; found: (N,) exit found by the march.
        p2: (N, 3) exit point (p1 where not found); t2: (N, 3) direction leaving the object.
        n2: (N, 3) outward shading normal at the exit (zeros where not found).
        uv2: (N, 2) texture coordinates at the exit.
        w2: (N,) exit weight: transmittance (1 - F2, rough: its energy), under TIR and
            ``tir: conserve`` as the rule says; 1 in the fallback.
        e_t2, e_r2: (N,) the exit interface's transmitted and reflected energies (rough,
            ``tir: conserve`` or internal bounces: averaged over the entry's transmitted
            lobe, :func:`torchrefract.optics.sgfit.spread_cosines`).
        var: (N,) per-axis angular variance of the entry's transmitted lobe (0 when smooth).
        path: (N,) length travelled inside; tir: (N,) total internal reflection somewhere.
        hidden: (N,) a sphere light between the eye and the object hides it.
    """

    idx: torch.Tensor
    batch: torch.Tensor
    d: torch.Tensor
    p1: torch.Tensor
    n1: torch.Tensor
    f1: torch.Tensor
    e1: torch.Tensor
    refl: torch.Tensor
    t1: torch.Tensor
    found: torch.Tensor
    p2: torch.Tensor
    n2: torch.Tensor
    uv2: torch.Tensor
    t2: torch.Tensor
    w2: torch.Tensor
    e_t2: torch.Tensor
    e_r2: torch.Tensor
    var: torch.Tensor
    path: torch.Tensor
    tir: torch.Tensor
    hidden: torch.Tensor


def background(g: GBuffer, lighting: Lighting) -> torch.Tensor:
    """(B*H*W, 3) radiance of the camera rays without the object: environment or a light
    (a light in front of the object included, one behind it excluded).

    Without sphere lights nothing can hide the object, so every object pixel's value is
    replaced by the method's and the pixels the object covers are left at zero (not looked
    up); with lights, every pixel is looked up (a light in front of the object shows)."""
    b, h, w = g.shape
    d_all = g.ray_dir.reshape(-1, 3)
    batch_all = torch.arange(b).repeat_interleave(h * w)
    if lighting.light_pos.shape[1] == 0:
        sel = where_true(~g.front.mask.reshape(-1))
        out = torch.zeros_like(d_all)
        bs = take(batch_all, sel)
        return put_(out, sel, incident_radiance(lighting, bs, take(g.eye, bs),
                                                take(d_all, sel)))
    max_dist = torch.where(g.front.mask.reshape(-1), g.front.dist.reshape(-1),
                           torch.full_like(d_all[:, 0], float("inf")))
    return incident_radiance(lighting, batch_all, take(g.eye, batch_all), d_all, max_dist)


def trace_paths(g: GBuffer, lighting: Lighting, materials: MaterialBatch,
                options: SpecularOptions) -> Paths:
    """Refract every object pixel's camera ray in, march to the exit, refract out.

    The rays follow the smooth surface; the interfaces' energies are those of the rough
    surface (``sgfit.interface_energies``: exact Fresnel when smooth, less the microfacet
    model's masking-shadowing loss when rough), at the front hit's roughness and at the
    exit's.
    """
    b, h, w = g.shape
    idx = g.front.mask.reshape(-1).nonzero(as_tuple=True)[0]  # compact: object pixels only
    bi = idx // (h * w)
    d = take(g.ray_dir.reshape(-1, 3), idx)  # (N, 3)
    p1 = take(g.front.position.reshape(-1, 3), idx)
    n1 = face_forward(take(g.front.normal.reshape(-1, 3), idx), d)
    eta = take(materials.ior, bi)  # (N,)
    hidden = light_in_front(lighting, bi, take(g.eye, bi), d,
                            take(g.front.dist.reshape(-1), idx))
    cos1 = -dot(d, n1)
    f1 = fresnel_dielectric(cos1, 1.0 / eta)
    t1, tir1 = refract(d, n1, 1.0 / eta)  # TIR at entry only when ior < 1
    ex = march_back(g, bi, p1, t1, steps=options.march_steps, refine=options.refine_steps)
    n2 = face_forward(ex.normal, t1)  # against the ray: points into the object
    cos2 = -dot(t1, n2)
    f2 = fresnel_dielectric(cos2, eta)
    t2, tir2 = refract(t1, n2, eta)
    tir2 = tir2 & ex.found
    if options.tir == "reflect":
        t2 = torch.where(tir2[:, None], reflect(t1, n2), t2)
    alpha1 = materials.roughness_at(bi, take(g.front.uv.reshape(-1, 2), idx))
    uv2 = interpolate(ex.bary, take(g.meshes.tri_uvs, ex.tri.clamp(min=0)))
    if bool((alpha1 > 0).any()):
        table = load_sg_table()
        dist_b = materials.distribution_index()
        dist = take(dist_b, bi)
        e_t1, e_r1 = interface_energies(table, cos1, eta, alpha1, dist, f1)
        alpha2 = torch.where(ex.found, materials.roughness_at(bi, uv2), alpha1)
        if options.tir == "conserve" or options.bounces.enabled:
            e_t2, e_r2, var = _spread_exit(table, cos1, eta, alpha1, dist, cos2, alpha2)
        else:  # the papers' rules: the energies of the sharp ray
            e_t2, e_r2 = interface_energies(table, cos2, 1.0 / eta, alpha2, dist, f2)
            var = torch.zeros_like(f2)
        esc = escape_fraction(table, materials.ior, dist_b, alpha2, bi) \
            if options.tir == "conserve" else None
    else:  # smooth: exact Fresnel, nothing lost
        e_t1, e_r1, e_t2, e_r2 = 1.0 - f1, f1, 1.0 - f2, f2
        esc = torch.ones_like(f2)
        var = torch.zeros_like(f2)
    one = torch.ones_like(f2)
    w2, _ = _last_interface(options.tir, tir2, e_t2, e_r2, esc)
    # Fallback where no exit was found: leave along the refracted direction.
    t2 = torch.where(ex.found[:, None], t2, t1)
    w2 = torch.where(ex.found, w2, one)
    p2 = torch.where(ex.found[:, None], ex.position, p1)
    path = torch.where(ex.found, ex.dist,
                       take((g.back.dist - g.front.dist).reshape(-1), idx).clamp(min=0.0))
    return Paths(idx=idx, batch=bi, d=d, p1=p1, n1=n1, f1=e_r1, e1=e_t1, refl=reflect(d, n1),
                 t1=t1, found=ex.found, p2=p2, n2=ex.normal, uv2=uv2, t2=t2, w2=w2,
                 e_t2=e_t2, e_r2=e_r2, var=var, path=path, tir=tir1 | tir2, hidden=hidden)


def _spread_exit(table, cos1, eta, alpha1, dist, cos2, alpha2):
    """The exit interface's energies averaged over the light arriving there: the entry's
    transmitted lobe (the SG table's, of sharpness k), at the incident cosines of
    :func:`torchrefract.optics.sgfit.spread_cosines` around its axis. The table's axis tilts from
    the refracted ray towards grazing (Walter's off-specular peak); the ray is marched, so
    the axis's own exit is estimated: its angle there is the ray's, plus the tilt (exact in
    a slab, where the two normals are parallel, and in a sphere, where a chord meets both
    interfaces at the same angle). Smooth entry points keep the ray.

    Returns e_t2, e_r2 and the lobe's variance 1 / k (0 where the entry is smooth), (N,).
    """
    rough = alpha1 > table.spec.alpha_min
    _, k1, tilt_axis, _ = sg_lookup(table, cos1, eta, alpha1, dist, "transmit")
    # cos(theta2 + tilt_axis - tilt_ray) by the angle-sum identities (no atan2: its
    # vectorized and scalar kernels differ in the last bit, and a batch must not change one)
    sin_t = torch.sqrt((1.0 - cos1 * cos1).clamp(min=1e-12)) / eta  # Snell
    cos_t = torch.sqrt((1.0 - sin_t * sin_t).clamp(min=1e-12))
    ca, sa = torch.cos(tilt_axis), torch.sin(tilt_axis)
    cos_d, sin_d = ca * cos_t + sa * sin_t, sa * cos_t - ca * sin_t  # of tilt_axis - tilt_ray
    sin2 = torch.sqrt((1.0 - cos2 * cos2).clamp(min=1e-12))
    c_axis = (cos2 * cos_d - sin2 * sin_d).clamp(min=0.0)
    c_axis = torch.where(rough, c_axis, cos2)
    var = torch.where(rough, 1.0 / k1, torch.zeros_like(k1))
    e_t, e_r = spread_interface_energies(table, c_axis, var, eta, alpha2, dist)
    return e_t, e_r, var


def path_passes(g: GBuffer, paths: Paths) -> dict[str, torch.Tensor]:
    b, h, w = g.shape
    exit_found = torch.zeros(b * h * w)
    tir = torch.zeros(b * h * w)
    put_(exit_found, paths.idx, paths.found.float())
    put_(tir, paths.idx, paths.tir.float())
    return {"exit_found": exit_found.view(b, h, w, 1), "tir": tir.view(b, h, w, 1)}


def render_specular(g: GBuffer, lighting: Lighting, materials: MaterialBatch,
                    options: SpecularOptions = SpecularOptions()
                    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Shade a G-buffer with two-sided specular refraction.

    Args:
        g: G-buffer of B views at (H, W) (sub-)pixels.
        lighting: environment maps and lights of the B scenes.
        materials: IOR, absorption, and roughness (for the interfaces' energies only:
            the rays follow the smooth surface).
        options: method settings.

    Returns:
        radiance: (B, H, W, 3) float32, background included.
        passes: ``exit_found`` and ``tir`` (B, H, W, 1) floats (1 where true, object pixels).
    """
    b, h, w = g.shape
    radiance = background(g, lighting)
    paths = trace_paths(g, lighting, materials, options)
    if paths.idx.numel() > 0:
        bi = paths.batch
        l_refl = incident_radiance(lighting, bi, paths.p1, paths.refl)
        att = torch.exp(-take(materials.absorption, bi) * paths.path[:, None])  # (N, 3)
        f1 = paths.f1[:, None]
        if options.bounces.enabled:
            n = paths.idx.numel()
            first = Arrival(pix=torch.arange(n), batch=bi, p=paths.p2, t=paths.t1,
                            normal=paths.n2, uv=paths.uv2, found=paths.found,
                            w=paths.e1[:, None] * att, var=paths.var)
            res = follow(g, first, _interface(lighting, materials, options.tir, paths),
                         materials.absorption, options.bounces, n, options.refine_steps)
            l_obj = f1 * l_refl + res.radiance
        else:
            l_trans = incident_radiance(lighting, bi, paths.p2, paths.t2)
            l_obj = f1 * l_refl + paths.e1[:, None] * paths.w2[:, None] * att * l_trans
        put_(radiance, paths.idx,
             torch.where(paths.hidden[:, None], take(radiance, paths.idx), l_obj))
    passes = path_passes(g, paths)
    if options.bounces.enabled:
        passes.update(bounce_passes(g, paths.idx, res if paths.idx.numel() else None))
    return radiance.view(b, h, w, 3), passes


def bounce_passes(g: GBuffer, idx: torch.Tensor, res) -> dict[str, torch.Tensor]:
    """``bounces`` (internal reflections followed) and ``bounce_residual`` (throughput left
    inside, mean over RGB) per pixel, (B, H, W, 1)."""
    b, h, w = g.shape
    out = {k: torch.zeros(b * h * w) for k in ("bounces", "bounce_residual")}
    if res is not None:
        put_(out["bounces"], idx, res.bounces.float())
        put_(out["bounce_residual"], idx, res.residual.float())
    return {k: v.view(b, h, w, 1) for k, v in out.items()}


def _interface(lighting: Lighting, materials: MaterialBatch, tir_mode: str, paths: Paths):
    """The interface seen from inside: (1 - F) leaves along the refracted ray, F is
    mirrored back inside (rough surfaces: the energies of ``sgfit.interface_energies``,
    averaged over the lobe of directions the light arrives with: the first exit's are the
    ``paths``', later ones carry the entry lobe's variance plus each reflection lobe's); at
    the last interface the ``tir`` rule lets TIR light leave (``clamp``: critical angle;
    ``reflect``: the mirror direction; ``conserve``: the reflected part leaves too, after
    the losses of the bounces not followed), as without bounces."""
    dist_b = materials.distribution_index()

    def shade(a: Arrival, k: int, last: bool) -> Shading:
        eta = materials.ior[a.batch]
        n_view = face_forward(a.normal, a.t)
        cos = -dot(a.t, n_view)
        f = fresnel_dielectric(cos, eta)
        t_out, tir = refract(a.t, n_view, eta)
        r = reflect(a.t, n_view)
        one, zero = torch.ones_like(f), torch.zeros_like(f)
        alpha = materials.roughness_at(a.batch, a.uv)
        rough = bool((alpha > 0).any())
        var = torch.zeros_like(f)
        if rough:
            table = load_sg_table()
            dist = dist_b[a.batch]
            if k == 0:  # the first exit: all paths, in order
                e_t, e_r = paths.e_t2, paths.e_r2
            else:
                e_t, e_r = spread_interface_energies(table, cos, a.var, eta, alpha, dist)
            if not last:  # the reflected lobe's spread, for the next interface
                k_r = sg_lookup(table, cos, 1.0 / eta, alpha, dist, "reflect")[1]
                var = a.var + torch.where(alpha > 0, 1.0 / k_r, zero)
        else:
            e_t, e_r = 1.0 - f, f
        # The fraction of trapped light that eventually leaves (escape_fraction; 1 when
        # smooth), looked up once where ``conserve``'s last interface or a lost ray needs it.
        lost_any = bool((~a.found).any())
        esc = escape_fraction(table, materials.ior, dist_b, alpha, a.batch) \
            if rough and (lost_any or (last and tir_mode == "conserve")) else one
        if last:
            if tir_mode == "reflect":
                t_out = torch.where(tir[:, None], r, t_out)
            w_out, refl = _last_interface(tir_mode, tir, e_t, e_r, esc)
        else:  # smooth TIR: e_t = 0, e_r = 1
            w_out, refl = e_t, e_r
        # Lost rays (no interface found) leave along their current direction, with what
        # light trapped inside eventually lets out (escape_fraction; 1 for smooth glass),
        # as rousiers' bounces do.
        t_out = torch.where(a.found[:, None], t_out, a.t)
        w_out = torch.where(a.found, w_out, esc)
        refl = torch.where(a.found, refl, zero)
        l_out = incident_radiance(lighting, a.batch, a.p, t_out)
        return Shading(radiance=a.w * w_out[:, None] * l_out, direction=r, reflectance=refl,
                       var=var)

    return shade


def _last_interface(tir_mode: str, tir: torch.Tensor, e_t: torch.Tensor, e_r: torch.Tensor,
                    esc: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``tir`` rule at the last interface followed (module docstring): the weight of the
    light leaving there, and the reflected part that does not (the residual).

    ``conserve``: the reflected part leaves too, after the losses of the bounces not
    followed (``esc``, :func:`torchrefract.shading.bounces.escape_fraction`; 1 when smooth), so the
    weight is continuous at TIR; ``reflect``: under TIR the reflected light leaves (along
    the mirror direction, which the caller sets); ``clamp``: under TIR all the interface
    keeps leaves at the critical angle.
    """
    zero = torch.zeros_like(e_t)
    if tir_mode == "conserve":
        return (e_t + e_r * esc).clamp(max=1.0), zero
    if tir_mode == "reflect":
        return torch.where(tir, e_r, e_t), torch.where(tir, zero, e_r)
    return torch.where(tir, (e_t + e_r).clamp(max=1.0), e_t), torch.where(tir, zero, e_r)


def light_in_front(lighting: Lighting, bi: torch.Tensor, o: torch.Tensor, d: torch.Tensor,
                   dist: torch.Tensor) -> torch.Tensor:
    """(N,) whether a sphere light lies between each camera ray's origin and the object."""
    if lighting.light_pos.shape[1] == 0:
        return torch.zeros_like(dist, dtype=torch.bool)
    t, _ = hit_lights(o, d, take(lighting.light_pos, bi), take(lighting.light_radius, bi),
                      take(lighting.light_radiance, bi))
    return t < dist
