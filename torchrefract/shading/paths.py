"""The refracted path through the two layers: entry refraction at the front hit, march to
the exit through the back-face buffer, exit refraction; shared by ``specular`` (whose module
docstring states the model) and ``prefiltered``."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrefract.geometry.gbuffer import GBuffer, interpolate
from torchrefract.kernels.index import put_, take
from torchrefract.kernels.march import march_back
from torchrefract.lighting.lights import Lighting
from torchrefract.optics.exit_rule import last_interface
from torchrefract.optics.materials import MaterialBatch
from torchrefract.optics.sgfit import (
    interface_energies,
    load_sg_table,
    sg_lookup,
    spread_interface_energies,
)
from torchrefract.optics.smooth import dot, face_forward, fresnel_dielectric, reflect, refract
from torchrefract.shading.background import light_in_front
from torchrefract.shading.bounces import escape_fraction


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


def trace_paths(g: GBuffer, lighting: Lighting, materials: MaterialBatch,
                options) -> Paths:
    """Refract every object pixel's camera ray in, march to the exit, refract out.

    The rays follow the smooth surface; the interfaces' energies are those of the rough
    surface (``sgfit.interface_energies``: exact Fresnel when smooth, less the microfacet
    model's masking-shadowing loss when rough), at the front hit's roughness and at the
    exit's.
    """
    idx, bi = g.object_index(), g.object_views()  # compact: object pixels only
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
            e_t2, e_r2, var = spread_exit(table, cos1, eta, alpha1, dist, cos2, alpha2)
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
    w2, _ = last_interface(options.tir, tir2, e_t2, e_r2, esc)
    # Fallback where no exit was found: leave along the refracted direction.
    t2 = torch.where(ex.found[:, None], t2, t1)
    w2 = torch.where(ex.found, w2, one)
    p2 = torch.where(ex.found[:, None], ex.position, p1)
    path = torch.where(ex.found, ex.dist,
                       take((g.back.dist - g.front.dist).reshape(-1), idx).clamp(min=0.0))
    return Paths(idx=idx, batch=bi, d=d, p1=p1, n1=n1, f1=e_r1, e1=e_t1, refl=reflect(d, n1),
                 t1=t1, found=ex.found, p2=p2, n2=ex.normal, uv2=uv2, t2=t2, w2=w2,
                 e_t2=e_t2, e_r2=e_r2, var=var, path=path, tir=tir1 | tir2, hidden=hidden)


def spread_exit(table, cos1, eta, alpha1, dist, cos2, alpha2):
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


__all__ = ["Paths", "path_passes", "trace_paths"]
