"""What a ray sees when it leaves the object: environment maps and spherical lights.

Sphere lights (SCENE_SPEC.md) emit ``radiance`` from their surface, are seen directly and
through the glass, hide the environment behind them and reflect nothing. The environment is
at infinity, so only the direction matters for it; lights need the ray origin too.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from . import envmap
from .scene import Scene


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
        num = max(len(s.lights) for s in scenes)
        b = len(scenes)
        pos, rad, le = torch.zeros(b, num, 3), torch.zeros(b, num), torch.zeros(b, num, 3)
        for i, s in enumerate(scenes):
            for j, l in enumerate(s.lights):
                pos[i, j], rad[i, j] = torch.tensor(l.position), l.radius
                le[i, j] = torch.tensor(l.radiance)
        return Lighting(
            texels=tuple(envmap.load_envmap(s.envmap.path) for s in scenes),
            paths=tuple(s.envmap.path for s in scenes),
            rotate_deg=torch.tensor([s.envmap.rotate_deg for s in scenes], dtype=torch.float32),
            scale=torch.tensor([s.envmap.scale for s in scenes], dtype=torch.float32),
            light_pos=pos, light_radius=rad, light_radiance=le)


    def pyramid(self, b: int):
        """The SG-pre-convolved pyramid of scene ``b``'s map (built once per file, cached)."""
        from .sgenv import sg_pyramid_for  # noqa: PLC0415

        return sg_pyramid_for(self.paths[b])


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
    bq = (oc * direction[:, None, :]).sum(-1)  # (N, L)
    c = (oc * oc).sum(-1) - radius * radius
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
        out[sel] = envmap.lookup(tex, direction[sel], lighting.rotate_deg[b],
                                 lighting.scale[b]).to(out.dtype)
    if lighting.light_pos.shape[1] > 0:
        t, le = hit_lights(origin, direction, lighting.light_pos[batch],
                           lighting.light_radius[batch], lighting.light_radiance[batch])
        hit = torch.isfinite(t)
        if max_dist is not None:
            hit = hit & (t < max_dist)
        out = torch.where(hit[:, None], le.to(out.dtype), out)
    return out


def incident_radiance_sg(lighting: Lighting, batch: torch.Tensor, origin: torch.Tensor,
                         direction: torch.Tensor, sharpness: torch.Tensor) -> torch.Tensor:
    """Environment radiance convolved with a normalized SG lobe around each direction.

    Args:
        lighting: the batch's lighting.
        batch: (N,) scene index; origin (N, 3); direction (N, 3); sharpness (N,) SG
            sharpness (inf = a plain lookup).

    Returns:
        (N, 3) radiance. Sphere lights are seen where the lobe's axis hits them (a sharp
        approximation: lights are not blurred by the lobe).
    """
    from .sgenv import sg_lookup_env  # noqa: PLC0415

    out = torch.zeros_like(direction)
    for b in range(len(lighting.texels)):
        sel = (batch == b).nonzero(as_tuple=True)[0]
        if sel.numel() == 0:
            continue
        out[sel] = sg_lookup_env(lighting.pyramid(b), direction[sel], sharpness[sel],
                                 lighting.rotate_deg[b], lighting.scale[b]).to(out.dtype)
    if lighting.light_pos.shape[1] > 0:
        t, le = hit_lights(origin, direction, lighting.light_pos[batch],
                           lighting.light_radius[batch], lighting.light_radiance[batch])
        out = torch.where(torch.isfinite(t)[:, None], le.to(out.dtype), out)
    return out
