"""Relighting: the image of a stored matte under any environment map, rotation and scale.

The image is linear in the environment (:mod:`torchrefract.matte.record`, eq. 1), so a
matte rendered once gives the image under another map without the G-buffer, the march or
the method:

    radiance = scale * sum_l weight_l * L_map(R_y(-rotate_deg) direction_l, sharpness_l)
               + lights

with the lookups of the renderer itself (a plain bilinear read for ``PLAIN`` lobes,
:func:`torchrefract.lighting.envmap.lookup`; the SG pyramid for the others,
:func:`torchrefract.lighting.sg_pyramid.sg_lookup_env`, de Rousiers et al. 2012 sec. 4.1),
and the rotation convention of the scenes (Mitsuba 3's: the map turned about world +Y,
SCENE_SPEC.md). With the render's own map, rotation and scale the result equals the render
up to float32 rounding where the matte folded nothing (``matte.folded == 0``). What it
cannot reproduce under another map: lobes folded into a neighbour (their light is read in the
neighbour's direction), and the sphere lights' term, kept as rendered (a light covering
part of a lobe hides that part of any map alike, so this is exact).

Example:
    >>> out = tr.render(scene.replace(passes={"matte": {}}))              # doctest: +SKIP
    >>> img = tr.relight(out, "assets/envmaps/lebombo.exr", rotate_deg=90)  # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path

import torch

from torchrefract.checks import ConfigError
from torchrefract.lighting import envmap as envmap_mod
from torchrefract.lighting.sg_pyramid import SGPyramid, build_sg_pyramid, sg_pyramid_for
from torchrefract.matte.matte import PLAIN, Matte, from_passes


def _as_matte(matte) -> Matte:
    if isinstance(matte, Matte):
        return matte
    passes = getattr(matte, "passes", matte)  # a RenderResult, or its passes
    if isinstance(passes, dict):
        return from_passes(passes)
    raise ConfigError(f"relight: matte must be a Matte, a RenderResult or a passes dict, got "
                      f"{type(matte).__name__}")


def _env(envmap) -> tuple[torch.Tensor, SGPyramid | None, str | None]:
    """(texels, pyramid or None (built on demand), path)."""
    from torchrefract.scene.model import EnvMap  # noqa: PLC0415

    if isinstance(envmap, EnvMap):
        envmap = envmap.path
    if isinstance(envmap, (str, Path)):
        path = str(envmap)
        return envmap_mod.load_envmap(path), None, path
    if isinstance(envmap, SGPyramid):
        return envmap.levels[0], envmap, None
    if torch.is_tensor(envmap) and envmap.dim() == 3 and envmap.shape[-1] == 3:
        return envmap, None, None
    raise ConfigError(f"relight: envmap must be a map file path, an EnvMap, an SGPyramid or "
                      f"an (H, W, 3) tensor, got {type(envmap).__name__}")


def _per_view(v, b: int, name: str) -> torch.Tensor:
    t = torch.as_tensor(v, dtype=torch.float32)
    if t.dim() == 0:
        t = t.expand(b)
    if t.shape != (b,) or not bool(torch.isfinite(t).all()):
        raise ConfigError(f"relight: {name} must be a finite number or one per view ({b}), "
                          f"got {v!r}")
    return t


def relight(matte, envmap, rotate_deg: float | torch.Tensor = 0.0,
            scale: float | torch.Tensor = 1.0) -> torch.Tensor:
    """The image of a matte under an environment map (module docstring).

    Args:
        matte: a :class:`~torchrefract.matte.matte.Matte`, a
            :class:`~torchrefract.render.RenderResult` rendered with ``passes: [matte]``,
            or its ``passes`` dict.
        envmap: a map file (``.exr``/``.hdr``), an ``EnvMap`` (its path only: give its
            rotation and scale here), an ``SGPyramid``, or (H, W, 3) texels (their SG
            pyramid is built here: seconds for a 1k map; pass a pyramid to reuse it).
        rotate_deg: rotation of the map about world +Y (degrees), scalar or (B,).
        scale: radiance multiplier, scalar or (B,).

    Returns:
        (B, H, W, 3) float32 linear RGB, always finite.
    """
    m = _as_matte(matte)
    b, h, w, n_lobes = m.sharpness.shape
    dev = m.weight.device  # the matte's (a GPU render's stays there)
    rot = _per_view(rotate_deg, b, "rotate_deg").to(dev)
    sc = _per_view(scale, b, "scale").to(dev)
    texels, pyr, path = _env(envmap)
    texels = texels.to(dev)
    pyr = None if pyr is None else pyr.to(dev)
    wt = m.weight.reshape(-1, 3)  # (B*H*W*L, 3)
    live = (wt != 0).any(-1).nonzero().squeeze(1)  # the used slots only
    wl, dl, kl = wt[live], m.direction.reshape(-1, 3)[live], m.sharpness.reshape(-1)[live]
    pix = live // n_lobes  # (S,) flat pixel
    view = pix // (h * w)
    val = torch.zeros_like(wl)
    plain_all = kl >= 0.5 * PLAIN
    for i in range(b):
        mine = view == i
        plain, soft = mine & plain_all, mine & ~plain_all
        if bool(plain.any()):
            sel = plain.nonzero().squeeze(1)
            val[sel] = envmap_mod.lookup(texels, dl[sel], rot[i], sc[i])
        if bool(soft.any()):
            if pyr is None:
                pyr = (sg_pyramid_for(path, device=dev) if path is not None
                       else build_sg_pyramid(texels))
            sel = soft.nonzero().squeeze(1)
            from torchrefract.lighting.sg_pyramid import sg_lookup_env  # noqa: PLC0415

            val[sel] = sg_lookup_env(pyr, dl[sel], kl[sel], rot[i], sc[i])
    img = m.lights.reshape(-1, 3).clone().index_add_(0, pix, val * wl)
    return torch.nan_to_num(img.view(b, h, w, 3), nan=0.0, posinf=0.0, neginf=0.0)


__all__ = ["relight"]
