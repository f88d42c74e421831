"""What a ray sees when it leaves the object: environment maps and spherical lights.

Sphere lights (SCENE_SPEC.md) emit ``radiance`` from their surface, are seen directly and
through the glass, hide the environment behind them and reflect nothing. The environment is
at infinity, so only the direction matters for it; lights need the ray origin too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torchrefract.kept import KeptByIdentity
from torchrefract.kernels import native
from torchrefract.kernels.index import put_, take
from torchrefract.lighting import envmap
from torchrefract.matte import record
from torchrefract.optics.smooth import dot
from torchrefract.scene.model import Scene


@dataclass(frozen=True)
class Lighting:
    """The lighting of B scenes.

    Attributes:
        texels: B lat-long maps, each (H_b, W_b, 3) (maps may differ in size).
        paths: B map files (for the cached SG pyramids of the rough methods).
        rotate_deg: (B,) map rotation about +Y.
        scale: (B,) radiance multipliers.
        light_pos: (B, L, 3) sphere light centers (L = most lights of any scene; padding has
            radius 0 and never hits).
        light_radius: (B, L).
        light_radiance: (B, L, 3).
    """

    texels: tuple[torch.Tensor, ...]
    paths: tuple[str, ...]
    rotate_deg: torch.Tensor
    scale: torch.Tensor
    light_pos: torch.Tensor
    light_radius: torch.Tensor
    light_radiance: torch.Tensor

    @staticmethod
    def from_scenes(scenes: list[Scene]) -> "Lighting":
        """The lighting of ``scenes``; the same object again for scenes that light alike
        (the same maps' tensors, rotations, scales and lights) as one of the last few
        batches: a dataset's or benchmark's batches differ by their cameras, and the
        fused kernels' structs are built once per Lighting (shading/fused.py). Its tensors
        must not be modified in place (``dataclasses.replace`` gives a new one)."""
        texels = tuple(envmap.load_envmap(s.envmap.path) for s in scenes)
        key = (tuple(id(t) for t in texels),
               tuple((s.envmap.path, s.envmap.rotate_deg, s.envmap.scale, s.lights)
                     for s in scenes))
        try:
            hit = _KEPT.get(texels[0], key)
        except TypeError:  # a value that does not hash: built anew
            return _lighting(scenes, texels)
        # (its texels are held by the kept Lighting: an id above cannot be another's)
        return hit if hit is not None else _KEPT.put(texels[0], key, _lighting(scenes, texels))

    def pyramid(self, b: int):
        """The SG-pre-convolved pyramid of scene ``b``'s map: built from the texels where
        a gradient is asked for (differentiable, a graph per call), or where they are an
        edited map on the CPU (kept per texel tensor and version); else the file's (built
        once per file, cached; texels moved to a GPU are taken for the file's)."""
        from torchrefract.lighting import sg_pyramid as sgp  # noqa: PLC0415

        tex = self.texels[b]
        if tex.requires_grad and torch.is_grad_enabled():
            return sgp.build_sg_pyramid(tex)  # (a graph per call: nothing kept)
        if tex.device.type != "cpu" or tex is envmap.load_envmap(self.paths[b]):
            return sgp.sg_pyramid_for(self.paths[b], device=self.scale.device)
        hit = _TEXEL_PYRAMIDS.get(tex, tex._version)
        return hit if hit is not None else _TEXEL_PYRAMIDS.put(
            tex, tex._version, sgp.build_sg_pyramid(tex.detach()))


_KEPT = KeptByIdentity(4)
"""The last few batches' Lighting (:meth:`Lighting.from_scenes`), per first map tensor."""
_TEXEL_PYRAMIDS = KeptByIdentity(4)
"""The pyramids of maps given as texels (:meth:`Lighting.pyramid`), per tensor and version."""


def _lighting(scenes: list[Scene], texels: tuple[torch.Tensor, ...]) -> Lighting:
    """:meth:`Lighting.from_scenes` built anew, with the scenes' loaded maps ``texels``."""
    num = max(len(s.lights) for s in scenes)
    b = len(scenes)
    pos, rad, le = torch.zeros(b, num, 3), torch.zeros(b, num), torch.zeros(b, num, 3)
    for i, s in enumerate(scenes):
        for j, l in enumerate(s.lights):
            pos[i, j], rad[i, j] = torch.tensor(l.position), l.radius
            le[i, j] = torch.tensor(l.radiance)
    return Lighting(
        texels=texels,
        paths=tuple(s.envmap.path for s in scenes),
        rotate_deg=torch.tensor([s.envmap.rotate_deg for s in scenes], dtype=torch.float32),
        scale=torch.tensor([s.envmap.scale for s in scenes], dtype=torch.float32),
        light_pos=pos, light_radius=rad, light_radiance=le)


def hit_lights(origin: torch.Tensor, direction: torch.Tensor, pos: torch.Tensor,
               radius: torch.Tensor, radiance: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest sphere light along each ray.

    Args:
        origin: (N, 3); direction: (N, 3) unit.
        pos: (N, L, 3); radius: (N, L); radiance: (N, L, 3) (per-ray copies of the lights).

    Returns:
        t: (N,) distance to the nearest light (inf if none).
        le: (N, 3) its radiance (zeros if none).
    """
    if pos.shape[1] == 0:
        return (torch.full(origin.shape[:1], float("inf"), dtype=origin.dtype),
                torch.zeros_like(origin))
    oc = origin[:, None, :] - pos  # (N, L, 3)
    bq = dot(oc, direction[:, None, :])  # (N, L)
    c = dot(oc, oc) - radius * radius
    disc = bq * bq - c
    sq = torch.sqrt(disc.clamp(min=0.0))
    t0, t1 = -bq - sq, -bq + sq
    t = torch.where(t0 > 0, t0, t1)  # the far root when the origin is inside the sphere
    valid = (disc >= 0) & (t > 0) & (radius > 0)
    t = torch.where(valid, t, torch.full_like(t, float("inf")))
    tmin, idx = t.min(dim=1)  # (N,)
    le = torch.gather(radiance, 1, idx[:, None, None].expand(-1, 1, 3))[:, 0]
    le = torch.where(torch.isfinite(tmin)[:, None], le, torch.zeros_like(le))
    return tmin, le


def incident_radiance(lighting: Lighting, batch: torch.Tensor, origin: torch.Tensor,
                      direction: torch.Tensor, max_dist: torch.Tensor | None = None
                      ) -> torch.Tensor:
    """Radiance arriving along rays that leave the object (environment or a light).

    Args:
        lighting: the batch's lighting.
        batch: (N,) int64 scene index of each ray.
        origin: (N, 3) ray origins; direction: (N, 3) unit directions.
        max_dist: (N,) optional; lights farther than this are hidden (e.g. behind the object
            for a camera ray), in which case zeros are returned for those rays' light part and
            the caller shades them.

    Returns:
        (N, 3) radiance.
    """
    out = torch.zeros_like(direction)
    for b, tex in enumerate(lighting.texels):
        sel = (batch == b).nonzero(as_tuple=True)[0]
        if sel.numel() == 0:
            continue
        put_(out, sel, envmap.lookup(tex, take(direction, sel), lighting.rotate_deg[b],
                                     lighting.scale[b]))
    # A matte render records the lookup and its weight (torchrefract.matte.record).
    out = record.tap(out, origin, direction, None, batch, "plain")
    if lighting.light_pos.shape[1] > 0:
        t, le = hit_lights(origin, direction, take(lighting.light_pos, batch),
                           take(lighting.light_radius, batch),
                           take(lighting.light_radiance, batch))
        hit = torch.isfinite(t)
        if max_dist is not None:
            hit = hit & (t < max_dist)
        out = torch.where(hit[:, None], le.to(out.dtype), out)
    return out


def incident_radiance_sg(lighting: Lighting, batch: torch.Tensor, origin: torch.Tensor,
                         direction: torch.Tensor, sharpness: torch.Tensor,
                         env: str = "sg") -> torch.Tensor:
    """Environment radiance convolved with a normalized SG lobe around each direction.

    Args:
        lighting: the batch's lighting.
        batch: (N,) scene index; origin (N, 3); direction (N, 3); sharpness (N,) SG
            sharpness (inf = a plain lookup).
        env: ``sg`` reads the SG-pre-convolved pyramid (exact), ``mip`` a box MIP at the
            lobe's variance 1 / sharpness (Lee et al. 2008, :mod:`.env_mips`).

    Returns:
        (N, 3) radiance. Sphere lights are convolved with the lobe too: the fraction of the
        lobe's mass each light's disc covers (:func:`sg_light_coverage`) sees the light,
        the rest the environment; a plain lookup (sharpness inf) sees a light where the
        axis hits it.
    """
    from torchrefract.lighting.sg_pyramid import sg_lookup_env  # noqa: PLC0415

    out = torch.zeros_like(direction)
    for b in range(len(lighting.texels)):
        sel = (batch == b).nonzero(as_tuple=True)[0]
        if sel.numel() == 0:
            continue
        if env == "mip":
            from torchrefract.lighting.env_mips import env_mips_for, mip_lookup  # noqa: PLC0415

            put_(out, sel, mip_lookup(env_mips_for(lighting.paths[b]), take(direction, sel),
                                      1.0 / take(sharpness, sel), lighting.rotate_deg[b],
                                      lighting.scale[b]))
            continue
        put_(out, sel, sg_lookup_env(lighting.pyramid(b), take(direction, sel),
                                     take(sharpness, sel), lighting.rotate_deg[b],
                                     lighting.scale[b]))
    # A matte render records the lookup and its weight (torchrefract.matte.record).
    out = record.tap(out, origin, direction, sharpness, batch, env)
    if lighting.light_pos.shape[1] > 0:
        pos, rad = take(lighting.light_pos, batch), take(lighting.light_radius, batch)
        le_all = take(lighting.light_radiance, batch)
        t, le = hit_lights(origin, direction, pos, rad, le_all)
        sharp = torch.where(torch.isfinite(t)[:, None], le.to(out.dtype), out)
        cover = sg_light_coverage(origin, direction, sharpness, pos, rad)  # (N, L)
        total = cover.sum(-1).clamp(max=1.0)
        cover = cover * (total / cover.sum(-1).clamp(min=1e-30))[:, None]
        soft = (1.0 - total)[:, None] * out + (cover[..., None] * le_all).sum(1).to(out.dtype)
        out = torch.where(torch.isinf(sharpness)[:, None], sharp, soft)
    return out


# 24-point Gauss-Legendre rule on [-1, 1] (numpy's leggauss), for the Rice integral below.
_GL_X, _GL_W = (torch.from_numpy(a) for a in np.polynomial.legendre.leggauss(24))


def sg_light_coverage(origin: torch.Tensor, direction: torch.Tensor, sharpness: torch.Tensor,
                      pos: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
    """Fraction of a normalized spherical Gaussian lobe's mass that falls on each sphere
    light's disc.

    de Rousiers et al. (sec. 5.2, eqs. 14-15) stand the light in by an SG of its own and take
    the SG inner product with the lobe; a sphere light is a uniform disc, whose exact
    coverage by the lobe this computes instead (so a sharp lobe inside the disc sees the
    light's full radiance, and none outside it).

    The lobe exp(k (v.p - 1)) (normalized over the sphere) and the light's cap (half-angle
    asin(r / d) around the direction to its center, at angle gamma from the axis p) are
    mapped to the plane by the chord length c(x) = sqrt(2 (1 - cos x)), which makes both
    exact: the lobe becomes an isotropic Gaussian of variance 1/k per axis (exp(-k c^2 / 2)
    = exp(k (cos x - 1))) and the cap a disc of area 2 pi (1 - cos theta) (its solid angle).
    The mass of a Gaussian on an off-center disc is the Rice distribution's CDF,

        P = int_0^R (r / s^2) exp(-(r - c_g)^2 / (2 s^2)) i0e(r c_g / s^2) dr,

    with s^2 = 1/k, R = c(theta), c_g = c(gamma); integrated with 24 Gauss-Legendre nodes
    on the part of [0, R] within 8 s of c_g (where the integrand lives), then divided by
    the lobe's normalization 1 - exp(-2k). Exact in the limits (a narrow lobe inside the
    disc: 1; a wide one: Omega times the lobe's density at the light), exact for a light on
    the axis, and within 0.008 of Monte Carlo sampling of the lobe off the axis (the chord
    map distorts an off-center cap; tests/test_lighting.py). A light the
    origin is inside covers everything.

    Args:
        origin, direction: (N, 3) lobe origin and unit axis; sharpness: (N,) k (inf allowed:
        treated as very sharp); pos: (N, L, 3); radius: (N, L) (0: padding, covers nothing).

    Returns:
        (N, L) coverage in [0, 1].
    """
    if direction.dtype == torch.float32 and origin.shape[0] > 0 and pos.shape[1] > 0:
        out = native.light_coverage(origin, direction, sharpness, pos, radius, _GL_X, _GL_W)
        if out is not None:  # the same integral in one kernel call (the fused kernels')
            return out
    dt = torch.float64
    to = pos.to(dt) - origin.to(dt)[:, None, :]
    d = to.norm(dim=-1).clamp(min=1e-30)
    r = radius.to(dt)
    cos_t = torch.sqrt((1.0 - (r / d) ** 2).clamp(min=0.0))  # cap half-angle's cosine
    cos_g = dot(to / d[..., None], direction.to(dt)[:, None, :]).clamp(-1.0, 1.0)
    big_r = torch.sqrt((2.0 * (1.0 - cos_t)).clamp(min=0.0))
    c_g = torch.sqrt((2.0 * (1.0 - cos_g)).clamp(min=0.0))
    k = sharpness.to(dt).clamp(max=1e12)[:, None].expand_as(d)
    s = torch.rsqrt(k.clamp(min=1e-12))
    a = (c_g - 8.0 * s).clamp(min=0.0)
    b = torch.minimum(big_r, c_g + 8.0 * s)
    half = ((b - a) * 0.5).clamp(min=0.0)
    x = (a + b)[..., None] * 0.5 + half[..., None] * _GL_X.to(a.device, dt)  # (N, L, 24)
    s2 = (s * s)[..., None]
    f = (x / s2) * torch.exp(-((x - c_g[..., None]) ** 2) / (2.0 * s2)) \
        * torch.special.i0e(x * c_g[..., None] / s2)
    mass = (f * _GL_W.to(a.device, dt)).sum(-1) * half / (-torch.expm1(-2.0 * k))
    cover = torch.where(d <= r, torch.ones_like(mass), mass.clamp(0.0, 1.0))
    cover = torch.where(r > 0, cover, torch.zeros_like(cover))
    return cover.to(direction.dtype)
