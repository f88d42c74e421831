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

Cost (docs/matte.md, "Speed"). Nothing of a relight depends on the map but the texels
read: per matte, once (:func:`prepare`), the used lobe slots, each lobe's normalized
direction, its row coordinate v (a rotation about +Y leaves it alone) and its azimuth at
rotation 0, u0 (a rotation about +Y shifts it); per pyramid layout (the level sharpnesses
and sizes follow the map's resolution), each lookup's level pair and blend weight, rows
and row weights, and each lookup's u0. Where the native kernels run (the CPU, no
gradient), a relight is then one pass of a C kernel (csrc/relight.c, :meth:`_Taps.values`)
that computes each lookup's u, column, four texel indices and weights op for op as the
tensor code (:meth:`_Group.reads`, the reference) and sums its 4 texels of a
channels-last copy of the map and its pyramid (made once per map) as ``embedding_bag``
does, nothing kept per rotation; elsewhere those indices and weights are kept for the
last 8 rotations and gathered by one ``embedding_bag``. Then a sum of the SG lobes' two
levels and a sum into the pixels.

Exactness. At the rotation the matte was rendered with (:func:`prepare`'s ``rotate_deg``;
a RenderResult's own), or at any rotation where that is unknown, u is the renderer's op
for op (``rotate_y``, ``direction_to_uv``), and so are the texel coordinates that follow
(the lookups' grid and ``grid_sample``'s unnormalization, in float32): the same to the
bit, only the weighted sums are added in another order (<= 4e-7 relative against
:func:`relight_reference`, the lookups one by one). At any other rotation u is u0 shifted
(:func:`_shifted`): within a few units in the last place of the renderer's u, not its bits
(measured up to 1.6e-4 relative on a background pixel next to a sun, 1.8e-5 on object
pixels, FLIP 0.0000 against the direct render: docs/matte.md), and without the C
library's ``atan2f`` per lobe, which was half the cost of a new rotation.

Example:
    >>> out = tr.render(scene.replace(passes={"matte": {}}))              # doctest: +SKIP
    >>> img = tr.relight(out, "assets/envmaps/lebombo.exr", rotate_deg=90)  # doctest: +SKIP
"""

from __future__ import annotations

import weakref
from collections import OrderedDict
from pathlib import Path

import torch
import torch.nn.functional as F

from torchrefract.checks import ConfigError
from torchrefract.kept import KeptByIdentity
from torchrefract.kernels import native
from torchrefract.lighting import envmap as envmap_mod
from torchrefract.lighting.sg_pyramid import (SGPyramid, _blend_weights, _pad_level,
                                              build_sg_pyramid, sg_pyramid_for)
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
        return _checked_texels(envmap), None, None
    raise ConfigError(f"relight: envmap must be a map file path, an EnvMap, an SGPyramid or "
                      f"an (H, W, 3) tensor, got {type(envmap).__name__}")


def _checked_texels(texels: torch.Tensor) -> torch.Tensor:
    """In-memory texels with the checks of a map file (finite, >= 0, bounded), in float32
    as a loaded map (a differentiable cast: a gradient still reaches the caller's tensor).
    Kept per tensor and version where no gradient flows, so that relighting with one map
    again checks and copies nothing, and its pyramid (:func:`_pyramid_of`, keyed by the
    float32 tensor) is found."""
    grad = texels.requires_grad
    hit = None if grad else _CHECKED.get(texels, texels._version)
    if hit is None:
        envmap_mod.validate_texels(texels.detach().cpu().float().numpy(), "relight: envmap")
        hit = texels.float()
        if not grad:
            _CHECKED.put(texels, texels._version, hit)
    return hit


_CHECKED = KeptByIdentity(4)
""":func:`_checked_texels`' memory: per texel tensor and version, its checked float32."""


def _per_view(v, b: int, name: str, minimum: float | None = None) -> torch.Tensor:
    t = torch.as_tensor(v, dtype=torch.float32)
    if t.dim() == 0:
        t = t.expand(b)
    if t.shape != (b,) or not bool(torch.isfinite(t).all()):
        raise ConfigError(f"relight: {name} must be a finite number or one per view ({b}), "
                          f"got {v!r}")
    if minimum is not None and bool((t < minimum).any()):
        raise ConfigError(f"relight: {name} must be >= {minimum:g} (as envmap.{name} in a "
                          f"scene), got {v!r}")
    return t


def relight(matte, envmap, rotate_deg: float | torch.Tensor = 0.0,
            scale: float | torch.Tensor = 1.0) -> torch.Tensor:
    """The image of a matte under an environment map (module docstring).

    What does not depend on the map is computed once per matte and pyramid layout and
    kept (:class:`Prepared`, :func:`prepare`). A relight is then one weighted gather of 4
    texels per lookup from a channels-last copy of the map and its pyramid (made once per
    map; a plain lobe is one lookup, an SG lobe two: its levels), with each lookup's texel
    indices and bilinear weights computed in the same pass by a C kernel where it runs,
    else by the tensor code and kept for the last few rotations (:meth:`_Taps.values`),
    and sums into the lobes and pixels. At the rendered rotation (or any, where it is
    unknown: a bare Matte or passes dict, unless prepared with :func:`prepare`'s
    ``rotate_deg``) the result equals
    :func:`relight_reference` (the renderer's lookups one by one) to float32 rounding: the
    texel coordinates are the same to the bit, the weighted sums are added in another
    order. At another rotation each lobe's u is its rotation-0 azimuth shifted (module
    docstring, "Exactness").

    Args:
        matte: a :class:`~torchrefract.matte.matte.Matte`, a
            :class:`~torchrefract.render.RenderResult` rendered with ``passes: [matte]``,
            its ``passes`` dict, or a :class:`Prepared` matte (:func:`prepare`; give it
            the rendered rotation where the matte is not a RenderResult).
        envmap: a map file (``.exr``/``.hdr``), an ``EnvMap`` (its path only: give its
            rotation and scale here), an ``SGPyramid``, or (H, W, 3) texels (their SG
            pyramid is built here: seconds for a 1k map; pass a pyramid to reuse it).
        rotate_deg: rotation of the map about world +Y (degrees), scalar or (B,).
        scale: radiance multiplier, scalar or (B,).

    Returns:
        (B, H, W, 3) float32 linear RGB, always finite.
    """
    texels, pyr, path = _env(envmap)
    if texels.requires_grad or (pyr is not None and pyr.base.requires_grad) or (
            not isinstance(matte, Prepared) and any(t.requires_grad for t in _anchors(matte))):
        # a gradient is wanted: the lookups one by one (nothing kept between calls)
        return relight_reference(matte.matte if isinstance(matte, Prepared) else matte,
                                 envmap, rotate_deg, scale)
    p = matte if isinstance(matte, Prepared) else prepare(matte)
    dev = p.device
    rot = _per_view(rotate_deg, p.b, "rotate_deg").to(dev)
    sc = _per_view(scale, p.b, "scale", minimum=0.0).to(dev)
    img = p.lights.clone()
    if p.size == 0:
        return img.view(p.b, p.h, p.w, 3)
    if p.n_soft > 0 and pyr is None:
        pyr = (sg_pyramid_for(path, device=dev) if path is not None
               else _pyramid_of(texels.to(dev)))
    if pyr is not None:
        pyr = pyr.to(dev)
    tex = _texels_last(pyr, texels.to(dev))
    base_hw = (texels.shape[0] + 1, texels.shape[1] + 2) if pyr is None else \
        tuple(pyr.base.shape[1:])
    taps = p.taps(base_hw, pyr)
    vals = taps.values(p, rot, tex)  # (L, 3)
    val = vals[:taps.n_plain]
    if p.n_soft:  # an SG lobe: its lower level's lookup plus its upper level's
        val = torch.cat([val, vals.index_select(0, taps.lo_at)
                         + vals.index_select(0, taps.hi_at)])
    val = val * (sc[:, None] if taps.view is None else sc.index_select(0, taps.view)[:, None])
    img.index_add_(0, taps.pix, val * taps.weight)
    return torch.nan_to_num(img.view(p.b, p.h, p.w, 3), nan=0.0, posinf=0.0, neginf=0.0)


def _shifted(u0: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """u of directions whose u at rotation 0 is ``u0`` (float64), for a rotation of the map
    by ``rot`` degrees about +Y (scalar or one per element), rounded to float32.

    ``envmap.rotate_y`` turns a direction by -rot before the lookup, which adds rot to its
    azimuth: with ``u = atan2(x, -z) / 2 pi`` (``direction_to_uv``; SCENE_SPEC.md), x =
    sin(phi), -z = cos(phi), and R_y(-rot) maps phi to phi + rot, so u = (u0 + rot / 360)
    mod 1. Within float32 rounding of the renderer's own u (a few units in its last place:
    see :meth:`Prepared.u`)."""
    u = u0 + rot.double() * (1.0 / 360.0)
    return (u - torch.floor(u)).float()


_INDEX = torch.int32
"""Texel indices into :func:`_texels_last`'s rows (< 2^31: 8M rows for a 1024 x 512 map's
pyramid): half the bytes of int64 to write per new rotation and to read per relight."""


class _Group:
    """Lookups that read one image (the padded map ``base`` or the ``atlas``, starting at
    row ``offset`` of :func:`_texels_last`) with one formula for the column. Per lookup,
    everything but the column is precomputed; the column follows from u by the
    arithmetic of the renderer's lookup and of ``grid_sample`` (bilinear,
    ``align_corners=True``, border padding), op for op in float32, so the texel
    coordinates are the renderer's to the bit."""

    def __init__(self, p: "Prepared", offset: int, lobe: torch.Tensor, blend: torch.Tensor,
                 *, plain: bool, hw: tuple[int, int], x0p1: torch.Tensor | None = None,
                 w: torch.Tensor | None = None, y0: torch.Tensor | None = None,
                 hh: torch.Tensor | None = None, map_hw: tuple[int, int] = (0, 0)):
        self.offset, self.lobe, self.plain = offset, lobe, plain
        v = p.v.index_select(0, lobe)
        # each lookup's lobe's azimuth at rotation 0 and view: a shifted u without a gather
        self.u0 = p.u0.index_select(0, lobe)
        self.view = None if p.view is None else p.view.index_select(0, lobe)
        rows, cols = hw  # the image's (padded) shape
        self.cols, self.numel = cols, rows * cols
        if plain:  # envmap.lookup: x = u W - 0.5 + 1, y = v (H - 1), on the (H, W + 2) pad
            h, self.w_map = map_hw
            y = v * (h - 1)
            gy = 2.0 * y / (h - 1) - 1.0
            size_y = h
        else:  # sg_pyramid.sg_lookup_env's sample(): x = x0 + 1 + u w - 0.5, y = y0 + v (h - 1)
            self.x0p1, self.w = x0p1, w
            y = y0 + v * (hh - 1)
            gy = 2 * y / (rows - 1) - 1
            size_y = rows
        iy = ((gy + 1.0) * ((size_y - 1) / 2)).clamp(0.0, float(size_y - 1))
        y_n = torch.floor(iy)
        n = iy - y_n
        # the rows' weights (upper, lower), times the level's share of the lobe
        self.sn = torch.stack([(1.0 - n) * blend, n * blend], 1)  # (n, 2)
        self.row = y_n.to(_INDEX) * cols + offset
        self.last = offset + self.numel - 1

    def select(self, order: torch.Tensor) -> None:
        """Keep the lookups ``order`` (in that order)."""
        for name in ("lobe", "sn", "row", "x0p1", "w", "u0", "view"):
            t = getattr(self, name, None)
            if t is not None and t.dim() >= 1:
                setattr(self, name, t.index_select(0, order))

    def _kernel_args(self, u: torch.Tensor | None, rot: torch.Tensor) -> dict:
        """What ``native.relight_reads`` / ``relight_values`` take of this group."""
        return dict(row=self.row, sn=self.sn, rot=rot, u0=self.u0, view=self.view, u=u,
                    lobe=self.lobe, plain=self.plain, w_map=getattr(self, "w_map", 0),
                    cols=self.cols, last=self.last, x0p1=getattr(self, "x0p1", None),
                    w=getattr(self, "w", None))

    def values(self, u: torch.Tensor | None, rot: torch.Tensor, tex: torch.Tensor,
               out: torch.Tensor) -> bool:
        """Each lookup's value (the weighted sum of its 4 texels of ``tex``) into ``out``
        (n, 3) by the C kernel (``native.relight_values``: :meth:`reads` and
        ``F.embedding_bag``'s sum in one pass, the same bits); ``False`` where it did not
        run (then :meth:`reads` and ``embedding_bag``)."""
        return native.relight_values(out, tex, **self._kernel_args(u, rot))

    def reads(self, u: torch.Tensor | None, rot: torch.Tensor,
              out: tuple[torch.Tensor, torch.Tensor] | None = None
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """(n, 4) texel indices and weights (written into ``out`` where given) for
        per-lobe u (S,) (:meth:`Prepared.u`), or where None, each lookup's u0 shifted for
        the rotations ``rot`` (B,) (:func:`_shifted`).

        The C kernel (``native.relight_reads``, csrc/relight.c) computes the same in one
        pass where it runs (the CPU, no gradient), op for op as the code below, which stays
        the reference and the fallback (tests/test_relight.py holds them equal)."""
        n = self.lobe.shape[0]
        if out is None:
            out = (torch.empty(n, 4, dtype=_INDEX, device=rot.device),
                   torch.empty(n, 4, dtype=torch.float32, device=rot.device))
        if native.relight_reads(*out, **self._kernel_args(u, rot)):
            return out
        if u is None:
            x = _shifted(self.u0, rot if self.view is None else rot.index_select(0, self.view))
        else:
            x = u.index_select(0, self.lobe)
        # x: u, then x, then gx, then ix, in place (the same ops in the same order, so the
        # same bits)
        if self.plain:  # x = u W - 0.5 + 1; gx = 2 x / (W + 1) - 1
            x.mul_(self.w_map).sub_(0.5).add_(1.0).mul_(2.0).div_(self.w_map + 1).sub_(1.0)
        else:  # x = x0 + 1 + u w - 0.5; gx = 2 x / (cols - 1) - 1
            x.mul_(self.w).add_(self.x0p1).sub_(0.5).mul_(2).div_(self.cols - 1).sub_(1)
        ix = x.add_(1.0).mul_((self.cols - 1) / 2).clamp_(0.0, float(self.cols - 1))
        x_w = torch.floor(ix)
        we = ix.sub_(x_w)  # the right column's weight
        e = 1.0 - we
        idx, wts = out
        # taps (row, col), (row, col + 1), (row + 1, col), (row + 1, col + 1); column by
        # column (a broadcast op over 4 was 5-20x slower). A tap right of / below the
        # image's last column / row has weight 0 exactly: any texel there will do, clamped
        # into the image. (Two bags, one per column, with the rows' weights fixed and the
        # columns blended after, wrote half as much per rotation but read each texel pair
        # twice: slower per relight, and no faster at a new rotation.)
        torch.add(self.row, x_w.to(_INDEX), out=idx[:, 0])
        for k, d in ((1, 1), (2, self.cols), (3, self.cols + 1)):
            torch.add(idx[:, 0], d, out=idx[:, k])
        idx.clamp_(max=self.last)
        for k, (r, c) in enumerate(((0, e), (0, we), (1, e), (1, we))):
            torch.mul(self.sn[:, r], c, out=wts[:, k])
        return out


class _Taps:
    """A prepared matte's lookups for one pyramid layout (the level sharpnesses and sizes
    follow the map's resolution): groups of lookups by image and formula (plain lobes;
    SG lobes' lower level on the map, on the atlas; their upper level), each SG level's
    share folded into its row weights. Within a group the lookups are sorted by the texel
    they read at rotation 0, so that the gather walks the texture in order (a rotation
    about +Y shifts the columns only). The lobes' order: the plain group's, then the SG
    lobes' (their lower and upper lookups at ``lo_at``, ``hi_at``)."""

    def __init__(self, p: "Prepared", base_hw: tuple[int, int], pyr: SGPyramid | None):
        dev = p.device
        h, w = base_hw[0] - 1, base_hw[1] - 2  # the map's texels
        offset = {"base": 0, "atlas": base_hw[0] * base_hw[1]}  # in _texels_last's rows
        self.groups: list[_Group] = []
        self._reads: OrderedDict = OrderedDict()
        rot0 = torch.zeros(p.b, device=dev)  # for the order only
        one = torch.ones((), device=dev)
        n_p, n_s = p.n_plain, p.n_soft

        def add(g: _Group) -> torch.Tensor:
            """Append g with its lookups sorted; their positions among all lookups."""
            order = torch.argsort(g.reads(None, rot0)[0][:, 0], stable=True)  # upper left
            g.select(order)
            at = sum(x.lobe.numel() for x in self.groups)
            self.groups.append(g)
            pos = torch.empty_like(order)
            pos[order] = at + torch.arange(order.numel(), device=dev)
            return pos  # position of the group's lookup k (before sorting)

        lobes = []
        if n_p:
            g = _Group(p, offset["base"], torch.arange(n_p, device=dev), one,
                       plain=True, hw=base_hw, map_hw=(h, w))
            add(g)
            lobes.append(g.lobe)  # sorted
        self.n_plain = n_p
        if n_s:
            i, t = _blend_weights(pyr, p.k_soft)  # the lower level, the upper one's share
            rects = torch.tensor(pyr.rects, dtype=torch.float32, device=dev)
            atlas_hw = tuple(pyr.atlas.shape[1:])

            def group(image, sel, level, blend):
                y0, x0, hh, ww = rects.index_select(0, level).unbind(-1)
                return _Group(p, offset[image], n_p + sel, blend,
                              plain=False, hw=base_hw if image == "base" else atlas_hw,
                              x0p1=x0 + 1, w=ww, y0=y0, hh=hh)

            on_map = i == 0
            self.lo_at = torch.empty(n_s, dtype=torch.long, device=dev)
            for image, sel in (("base", on_map.nonzero().squeeze(1)),
                               ("atlas", (~on_map).nonzero().squeeze(1))):
                if sel.numel():
                    self.lo_at[sel] = add(group(image, sel, i.index_select(0, sel),
                                                1 - t.index_select(0, sel)))
            every = torch.arange(n_s, device=dev)
            self.hi_at = add(group("atlas", every, i + 1, t))
            lobes.append(n_p + every)
        self.n_lookups = sum(g.lobe.numel() for g in self.groups)
        self.offsets = torch.arange(0, 4 * self.n_lookups, 4, dtype=_INDEX,
                                    device=dev)  # a bag of 4 texels per lookup
        order = torch.cat(lobes)  # the prepared lobe of each value
        self.pix = p.pix.index_select(0, order)
        self.weight = p.weight.index_select(0, order)
        self.view = None if p.view is None else p.view.index_select(0, order)

    def values(self, p: "Prepared", rot: torch.Tensor, tex: torch.Tensor) -> torch.Tensor:
        """(n_lookups, 3) every lookup's value: the weighted sum of its 4 texels of ``tex``
        (:func:`_texels_last`) at rotations (B,). Where the C kernel runs (the CPU, no
        gradient), computed in one pass from each lookup's u, nothing kept per rotation
        but the renderer's u of the exact views (:meth:`Prepared.u`); else ``embedding_bag``
        over :meth:`reads` (kept for the last 8 rotations). The same bits either way
        (measured; the kernel sums as ``embedding_bag`` does on the CPU, with fused
        multiply-adds)."""
        if native.available() and tex.device.type == "cpu":
            exact = p.exact_views(rot)
            u = p.u(rot, exact) if any(exact) else None  # else shifted per lookup
            vals = torch.empty(self.n_lookups, 3, dtype=tex.dtype)
            at = 0
            for g in self.groups:
                n = g.lobe.numel()
                if not g.values(u, rot, tex, vals[at:at + n]):
                    break
                at += n
            else:
                return vals
        idx, wts = self.reads(p, rot)
        return F.embedding_bag(idx, tex, self.offsets, mode="sum", per_sample_weights=wts)

    def reads(self, p: "Prepared", rot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Every lookup's four texel indices (into :func:`_texels_last`'s rows) and
        weights, lookup-major, for rotations (B,) (kept for the last 8 rotations)."""
        exact = p.exact_views(rot)
        key = (tuple(rot.tolist()), exact)
        hit = self._reads.get(key)
        if hit is None:
            u = p.u(rot, exact) if any(exact) else None  # else shifted per lookup
            hit = (torch.empty(self.n_lookups, 4, dtype=_INDEX, device=rot.device),
                   torch.empty(self.n_lookups, 4, dtype=torch.float32, device=rot.device))
            at = 0
            for g in self.groups:
                n = g.lobe.numel()
                g.reads(u, rot, (hit[0][at:at + n], hit[1][at:at + n]))
                at += n
            hit = (hit[0].view(-1), hit[1].view(-1))
            self._reads[key] = hit
            while len(self._reads) > 8:
                self._reads.popitem(last=False)
        self._reads.move_to_end(key)
        return hit


class Prepared:
    """What relighting a matte needs that does not depend on the map: its used lobe slots
    (pixel, view, RGB weight), each lobe's normalized direction (as the lookups normalize
    it), its row coordinate v and its rotation-free azimuth u0 (a rotation about +Y leaves
    v unchanged and shifts u), and per pyramid layout each lookup's level pair, blend
    weight, row and row weights (:class:`_Taps`). Lobes are ordered plain ones first, then
    the SG lobes. Made by :func:`prepare` (kept for the last few mattes); may be passed to
    :func:`relight` in place of the matte.

    ``rotate_deg``: the rotation the matte was rendered with (scalar or one per view), or
    None where unknown. A view relit at its rendered rotation, or at any rotation where
    it is unknown, gets the renderer's u op for op (:meth:`u`): its relit image is the
    render to float32 rounding. Every other rotation shifts u0."""

    def __init__(self, m: Matte, rotate_deg: float | torch.Tensor | None = None):
        self.matte = m
        b, h, w, n_lobes = m.sharpness.shape
        self.b, self.h, self.w = b, h, w
        self.device = m.weight.device
        self.rendered = None if rotate_deg is None else \
            _per_view(rotate_deg, b, "the rendered rotate_deg").to(self.device)
        wt = m.weight.reshape(-1, 3)
        live = (wt != 0).any(-1).nonzero().squeeze(1)  # the used slots only
        k = m.sharpness.reshape(-1).index_select(0, live)
        plain = k >= 0.5 * PLAIN
        self.n_plain = int(plain.sum())
        soft = (~plain).nonzero().squeeze(1)
        order = torch.cat([plain.nonzero().squeeze(1), soft])
        live = live[order]
        self.size = live.numel()
        self.n_soft = self.size - self.n_plain
        self.k_soft = k[soft]
        self.weight = wt.index_select(0, live)
        self.pix = live // n_lobes
        self.view = None if b == 1 else self.pix // (h * w)
        d = m.direction.reshape(-1, 3).index_select(0, live)
        self.d = d / d.norm(dim=-1, keepdim=True).clamp(min=1e-30)  # as both lookups do
        self.v = envmap_mod.direction_to_uv(self.d)[:, 1].contiguous()  # the lookups' v
        # u at rotation 0 in float64, so that a shifted u (:func:`_shifted`) rounds once
        self.u0 = envmap_mod.direction_to_uv(self.d.double())[:, 0].contiguous()
        self.lights = m.lights.reshape(-1, 3).clone()
        self._taps: OrderedDict = OrderedDict()
        self._u: OrderedDict = OrderedDict()

    def taps(self, base_hw, pyr: SGPyramid | None) -> _Taps:
        """The lookups for a map of padded shape ``base_hw`` and its pyramid (kept for the
        last few layouts)."""
        key = (tuple(base_hw),) if self.n_soft == 0 else \
            (tuple(base_hw), tuple(pyr.atlas.shape[1:]), pyr.rects, pyr.sharpness)
        hit = self._taps.get(key)
        if hit is None:
            hit = self._taps[key] = _Taps(self, tuple(base_hw), pyr)
            while len(self._taps) > 4:
                self._taps.popitem(last=False)
        self._taps.move_to_end(key)
        return hit

    def forget_rotations(self) -> None:
        """Drop what is kept per rotation (each lobe's u, the taps' texel indices and
        weights): the next relight computes them again (scripts/relight_bench.py times
        that)."""
        self._u.clear()
        for t in self._taps.values():
            t._reads.clear()

    def exact_views(self, rot: torch.Tensor) -> tuple[bool, ...]:
        """Per view, whether rotation ``rot`` (B,) takes the renderer's u op for op: at the
        rendered rotation, or anywhere where that is unknown."""
        if self.rendered is None:
            return (True,) * self.b
        return tuple((rot == self.rendered).tolist())

    def u(self, rot: torch.Tensor, exact: tuple[bool, ...] | None = None) -> torch.Tensor:
        """(S,) float32 u of every lobe for per-view rotations (B,); kept for the last 8.

        The views in ``exact`` (default :meth:`exact_views`) take the renderer's own
        functions (``rotate_y``, ``direction_to_uv``): the same bits as its lookups, at the
        cost of the C library's atan2f per lobe. The others take u0 shifted
        (:func:`_shifted`), within a few units in the last place of those (atan2f's own
        last bit moves reads next to a sun by up to 3e-4 relative: docs/matte.md, "Speed").
        Where no view is exact, the taps shift each lookup's u0 instead (no gather)."""
        exact = self.exact_views(rot) if exact is None else exact
        key = (tuple(rot.tolist()), exact)
        hit = self._u.get(key)
        if hit is not None:
            self._u.move_to_end(key)
            return hit
        u = _shifted(self.u0, rot if self.view is None else rot.index_select(0, self.view))
        for i in (i for i in range(self.b) if exact[i]):
            sel = None if self.view is None else (self.view == i).nonzero().squeeze(1)
            d = self.d if sel is None else self.d.index_select(0, sel)
            # the lookups' own: rotate_y(d, -rot) of an (N, 3) d, then atan2 of its strided
            # columns (torch's scalar loop, the C library's atan2f; its vectorized SLEEF
            # loop differs in the last bit for ~5% of the lobes)
            ui = envmap_mod.direction_to_uv(envmap_mod.rotate_y(d, -rot[i]))[:, 0]
            if sel is None:
                u = ui
            else:
                u[sel] = ui
        self._u[key] = u
        while len(self._u) > 8:
            self._u.popitem(last=False)
        return u


_PREPARED: "OrderedDict[tuple, tuple[list, Prepared]]" = OrderedDict()


def _anchors(matte) -> list[torch.Tensor]:
    if isinstance(matte, Matte):
        return [matte.direction, matte.sharpness, matte.weight, matte.lights]
    passes = getattr(matte, "passes", matte)
    if isinstance(passes, dict):
        return [t for k, t in sorted(passes.items())
                if k.startswith("matte.") and torch.is_tensor(t)]
    return []


def prepare(matte, rotate_deg: float | torch.Tensor | None = None) -> Prepared:
    """The map-independent part of relighting ``matte`` (a Matte, a RenderResult or its
    passes), computed once: kept for the 4 most recent mattes (keyed by their tensors and
    those tensors' versions: an in-place change prepares again, and by ``rotate_deg``).

    ``rotate_deg``: the rotation the matte was rendered with (scalar or per view; a
    RenderResult's own scenes' when not given), where a relight takes the renderer's u op
    for op (:class:`Prepared`); None where unknown: then every rotation does (exact, but a
    new rotation costs the C library's atan2f per lobe: docs/matte.md, "Speed")."""
    if rotate_deg is None and getattr(matte, "scenes", None):
        rotate_deg = [s.envmap.rotate_deg for s in matte.scenes]
    rendered = None if rotate_deg is None else tuple(torch.as_tensor(
        rotate_deg, dtype=torch.float32).reshape(-1).tolist())
    anchors = _anchors(matte)
    key = (tuple((id(t), t._version) for t in anchors), rendered)
    hit = _PREPARED.get(key) if anchors else None
    if hit is not None and all(r() is t for r, t in zip(hit[0], anchors)):
        _PREPARED.move_to_end(key)
        return hit[1]
    p = Prepared(_as_matte(matte), rotate_deg)
    if anchors:
        _PREPARED[key] = ([weakref.ref(t) for t in anchors], p)
        while len(_PREPARED) > 4:
            _PREPARED.popitem(last=False)
    return p


_BUILT: "OrderedDict[int, tuple]" = OrderedDict()


def _pyramid_of(texels: torch.Tensor) -> SGPyramid:
    """The SG pyramid of in-memory texels (kept for the last two, keyed by the tensor and
    its version)."""
    hit = _BUILT.get(id(texels))
    if hit is not None and hit[0]() is texels and hit[1] == texels._version:
        return hit[2]
    with torch.no_grad():
        pyr = build_sg_pyramid(texels)
    _BUILT[id(texels)] = (weakref.ref(texels), texels._version, pyr)
    while len(_BUILT) > 2:
        _BUILT.popitem(last=False)
    return pyr


_LAST: "OrderedDict[int, tuple]" = OrderedDict()


def _texels_last(pyr: SGPyramid | None, texels: torch.Tensor) -> torch.Tensor:
    """(texels, 3) channels-last rows of the padded map (the pyramid's level 0, or the
    texels padded alike where no pyramid is needed), then of the pyramid's atlas: what
    ``embedding_bag`` gathers from (a texel's three channels in one read). Kept for the
    last 4 maps, as ``sg_pyramid_for`` keeps their pyramids (keyed by the tensors and
    their versions): the copy (95 MB, 0.05-0.1 s for a 1024 x 512 map's pyramid) is made
    once per map, not per relight."""
    anchors = (texels,) if pyr is None else (pyr.base, pyr.atlas)
    key = tuple(id(t) for t in anchors)
    hit = _LAST.get(key)
    if hit is not None and all(r() is t and v == t._version
                               for (r, v), t in zip(hit[0], anchors)):
        _LAST.move_to_end(key)
        return hit[1]
    parts = [_pad_level(texels.permute(2, 0, 1))] if pyr is None else [pyr.base, pyr.atlas]
    out = torch.cat([t.permute(1, 2, 0).reshape(-1, 3) for t in parts])
    _LAST[key] = ([(weakref.ref(t), t._version) for t in anchors], out)
    while len(_LAST) > 4:
        _LAST.popitem(last=False)
    return out


def relight_reference(matte, envmap, rotate_deg: float | torch.Tensor = 0.0,
                      scale: float | torch.Tensor = 1.0) -> torch.Tensor:
    """The relit image by the renderer's own lookups, lobe by lobe (slow; what
    :func:`relight` computes, kept to check it, and the path a gradient takes). Arguments
    and result as :func:`relight`, but ``matte`` not a :class:`Prepared` one."""
    m = _as_matte(matte)
    b, h, w, n_lobes = m.sharpness.shape
    dev = m.weight.device  # the matte's (a GPU render's stays there)
    rot = _per_view(rotate_deg, b, "rotate_deg").to(dev)
    sc = _per_view(scale, b, "scale", minimum=0.0).to(dev)
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


__all__ = ["Prepared", "prepare", "relight", "relight_reference"]
