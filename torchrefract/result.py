"""A render's result, and how one pass over a built G-buffer becomes it: the method's
shading (in tiles where the budget asks, and adaptive shading's levels), the geometry's,
the material's and the method's passes, the box filter over sub-pixels; and results of
parts of a batch merged. Shared by :mod:`torchrefract.render` (a batch in one pass or in
chunks) and :mod:`torchrefract.large` (a frame in strips)."""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass, field

import torch

from torchrefract import tiles
from torchrefract.geometry import adaptive
from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.kernels import native
from torchrefract.kernels.index import put_, take
from torchrefract.matte import render_hook
from torchrefract.optics.materials import MaterialBatch
from torchrefract.scene import Scene
from torchrefract.shading import fused
from torchrefract.stages import collect


@dataclass(frozen=True)
class RenderResult:
    """Output of :func:`torchrefract.render.render` for B scenes at (H, W) pixels.

    Attributes:
        radiance: (B, H, W, 3) float32 linear RGB, background included, always finite.
        coverage: (B, H, W) float32 object coverage in [0, 1] (the EXR's A channel).
        passes: name -> (B, H, W, C) float32: ``depth_front``, ``depth_back`` (camera-space
            depth), ``normal_front``, ``normal_back`` (world, unit before filtering),
            ``thickness`` (distance between the layers along the view ray), ``roughness`` and
            ``ior`` (the material on object pixels), and the method's own buffers. Passes
            are averaged over the covered sub-pixels; 0 where uncovered.
        scenes: the B scenes, as rendered.
        timings: seconds per stage for the whole batch: ``load`` (meshes, maps), ``gbuffer``,
            ``shading`` (the method, which includes ``march``, the ray marches, and ``mips``,
            the back layer's mip pyramids; :mod:`torchrefract.stages`), ``total``.
        blends: ``auto`` only: per scene the (method, options, weight) of every variant
            whose image went into it (weights add up to 1; passes are blended alike).
        predictions: ``auto`` only: per scene what its table predicted (``Choice.record``:
            the image's FLIP against converged truth and ms per frame, the most accurate
            candidate's FLIP, the tolerance, the table scenes it was read from), or None
            without a table.
    """

    radiance: torch.Tensor
    coverage: torch.Tensor
    passes: dict[str, torch.Tensor]
    scenes: tuple[Scene, ...]
    timings: dict[str, float] = field(default_factory=dict)
    blends: tuple[tuple[tuple[str, dict, float], ...], ...] | None = None
    predictions: tuple[dict | None, ...] | None = None


def box(x: torch.Tensor, n: int) -> torch.Tensor:
    """Average n x n blocks of a (B, H, W, C) tensor -> (B, H/n, W/n, C).

    The sub-pixels are summed in row-major order and divided by n * n: the operations of
    ``F.avg_pool2d`` (the same bits, tests/test_box_filter.py), without its cost on this layout
    (8 x 512 x 512 x 1 floats, 2 threads: 1.0 ms against 6.0)."""
    if n == 1:
        return x
    out = native.box(x, n)  # (csrc/box.c: the same bits, one pass)
    if out is not None:
        return out
    b, h, w, c = x.shape
    y = x.reshape(b, h // n, n, w // n, n, c)  # (B, H/n, n, W/n, n, C)
    s = y[:, :, 0, :, 0]
    for i in range(n):
        for j in range(n):
            if i or j:
                s = s + y[:, :, i, :, j]
    return s / (n * n)


BoxCache = dict
"""Per render pass: each mask as a float tensor and its box average (the covered fraction),
keyed by (id(mask), dtype), shared by the passes averaged over the same mask."""


def mask_box(mask: torch.Tensor, n: int, dtype: torch.dtype, cache: BoxCache | None
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, H, W, 1) ``mask`` as ``dtype``, and its box average."""
    key = (id(mask), dtype)
    if cache is not None and key in cache:
        return cache[key]
    m = mask[..., None].to(dtype)
    out = (m, box(m, n))
    if cache is not None:
        cache[key] = out
    return out


def masked_box(x: torch.Tensor, mask: torch.Tensor, n: int, cache: BoxCache | None = None
                ) -> torch.Tensor:
    """Average of x over the covered sub-pixels of each pixel (0 where none is covered)."""
    out = native.box(x, n, mask)  # (csrc/box.c: the same bits, one pass)
    if out is not None:
        return out
    if n == 1:  # one sub-pixel per pixel: x where covered (x * 1 / 1 is x), else 0
        return torch.where(mask[..., None], x, torch.zeros((), dtype=x.dtype))
    m, den = mask_box(mask, n, x.dtype, cache)
    num = box(x * m, n)
    return torch.where(den > 0, num / den.clamp(min=1e-12), torch.zeros_like(num))


def plan_box(x: torch.Tensor, n: int, uniform: torch.Tensor,
             mask: torch.Tensor | None = None, cache: BoxCache | None = None) -> torch.Tensor:
    """:func:`box` (``mask`` None) or :func:`masked_box` of ``x`` (B, H, W, C) whose
    ``uniform`` pixels (B, H/n, W/n; adaptive.plan: covered at every sub-pixel) hold their
    value at their first sub-pixel only: the bits those give had it been copied to the
    others, without the copies (the first sub-pixel summed n*n times in box's order;
    masked, times a mask of ones over a coverage of one). csrc/box.c reads only the first
    sub-pixel of a uniform pixel; the tensor code filters every pixel and picks."""
    out = native.box(x, n, mask, uniform)
    if out is not None:
        return out
    v = x[:, ::n, ::n]
    s = v
    for _ in range(n * n - 1):
        s = s + v
    rest = box(x, n) if mask is None else masked_box(x, mask, n, cache)
    return torch.where(uniform[..., None], s / (n * n), rest)


def all_finite(x: torch.Tensor) -> bool:
    """Whether every value of ``x`` is finite: the sum of finite values is finite unless it
    overflows, where the elementwise test decides (NaN and Inf make the sum non-finite)."""
    with torch.no_grad():
        return bool(torch.isfinite(x.sum())) or bool(torch.isfinite(x).all())


MASKS = (None, "front", "back", "both")
"""The masks a pass is averaged over (:func:`filter_passes`' requests): none, a layer's
coverage, or both layers'."""


def filter_passes(g: GBuffer, requests: dict[str, tuple], uniform: torch.Tensor | None,
                  cache: BoxCache | None = None) -> dict[str, torch.Tensor]:
    """Each request ``name -> (x, mask, plan)`` filtered to pixels: x (B, H, W, C) (None:
    the mask's covered fraction, (B, H/n, W/n, 1)) averaged over ``mask``'s (one of MASKS)
    covered sub-pixels, ``plan``: with a supersampled plan's ``uniform`` pixels holding
    their first sub-pixel (:func:`plan_box`). At 2 x 2 one pass of csrc/box.c filters them
    all (each mask's coverage counted once per pixel); else, or where it does not run, one
    request at a time. The bits are the same either way."""
    n = g.supersample
    kinds = {m: i for i, m in enumerate(MASKS)}
    if any(x is None and m is None for x, m, _ in requests.values()):
        raise ValueError("filter_passes: a coverage request (x None) needs a mask")
    items = [(x, kinds[m], bool(p) and uniform is not None) for x, m, p in requests.values()]
    out = native.boxes(items, (g.front.mask, g.back.mask), uniform) if n == 2 else None
    if out is not None:
        return dict(zip(requests, out))
    masks = {"front": g.front.mask, "back": g.back.mask}
    if any(m == "both" for _, m, _ in requests.values()):
        masks["both"] = g.front.mask & g.back.mask
    done = {}
    for name, (x, m, p) in requests.items():
        mask = masks.get(m)
        if x is None:
            done[name] = mask_box(mask, n, torch.float32, cache)[1]
        elif p and uniform is not None:
            done[name] = plan_box(x, n, uniform, mask, cache)
        else:
            done[name] = box(x, n) if mask is None else masked_box(x, mask, n, cache)
    return done


def geometry_requests(g: GBuffer, thick: torch.Tensor | None = None) -> dict[str, tuple]:
    """The geometry passes' :func:`filter_passes` requests: each layer's depth and normal
    over its own coverage, the thickness between them over both (``thick``: given)."""
    if thick is None:
        thick = (g.back.dist - g.front.dist).clamp_(min=0.0)[..., None]  # (in place)
    return {"depth_front": (g.front.depth[..., None], "front", False),
            "depth_back": (g.back.depth[..., None], "back", False),
            "normal_front": (g.front.normal, "front", False),
            "normal_back": (g.back.normal, "back", False),
            "thickness": (thick, "both", False)}


def _one_sample(g: GBuffer, rough: torch.Tensor, materials: MaterialBatch
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """At one sample per pixel: the front coverage as 0 / 1 and the geometry and material
    passes (the layers are zero where empty; the thickness is masked by both layers, the
    material by the front's), by csrc/box.c's one sweep or the tensor code (same bits)."""
    ior = materials.ior
    made = native.one_sample_passes(g.front.mask, g.back.mask, g.front.dist, g.back.dist,
                                    rough, ior)
    if made is not None:
        fm, thick, rough_px, ior_px = made
        done = {k: x for k, (x, _, _) in geometry_requests(g, thick).items()}
    else:
        fm = g.front.mask[..., None].to(torch.float32)
        requests = geometry_requests(g)
        done = {k: x for k, (x, _, _) in requests.items()}
        done.update(filter_passes(g, {"thickness": requests["thickness"]}, None))
        rough_px, ior_px = fm * rough, fm * ior[:, None, None, None]
    return fm, {**done, "roughness": rough_px, "ior": ior_px}


def front_roughness(g: GBuffer, materials: MaterialBatch) -> torch.Tensor:
    """The roughness at each front (sub-)pixel, (B, H, W), or (B, 1, 1) where no scene of
    the batch has a map (then it is each view's own)."""
    if not materials.has_maps:
        return materials.roughness[:, None, None]
    b, h, w = g.shape
    return materials.roughness_at(torch.arange(b).repeat_interleave(h * w),
                                  g.front.uv.reshape(-1, 2)).view(b, h, w)


def pixel_passes(g: GBuffer, radiance: torch.Tensor, method_passes: dict[str, torch.Tensor],
                 materials: MaterialBatch, uniform: torch.Tensor | None
                 ) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
    """A render pass's (sub-)pixel buffers as pixels: the radiance (B, H/n, W/n, 3), the
    front coverage (B, H/n, W/n, 1) and the passes, geometry, material (what a model
    trained on the data may regress, per object pixel) and the method's, in that order.
    ``uniform``: a supersampled plan's pixels that hold their values at their first
    sub-pixel. ``method_passes`` is emptied (each buffer let go once filtered)."""
    n = g.supersample
    rough = front_roughness(g, materials)[..., None]
    if n == 1:  # the layers are zero where empty, and so are the method's passes off the
        # object (methods.base.Shaded)
        coverage, done = _one_sample(g, rough, materials)
        passes = {**done, **method_passes}
        method_passes.clear()
        return radiance, coverage, passes
    cache: BoxCache = {}  # the masks' box averages, computed once for all passes
    requests = geometry_requests(g)
    materials_px = (("roughness", rough), ("ior", materials.ior[:, None, None, None]))
    order = [*requests, "roughness", "ior", *method_passes]
    # the front coverage as 0 / 1 where a pass is taken per sub-pixel (a map)
    fm = g.front.mask[..., None].to(torch.float32) if rough.shape[1] != 1 else None
    for name, v in materials_px:
        if v.shape[1] != 1:  # a map: the mean over the pixel's covered sub-pixels
            requests[name] = (fm * v, "front", False)
    requests.update((k, (v, "front", True)) for k, v in method_passes.items())
    requests["radiance"] = (radiance, None, True)
    requests["coverage"] = (None, "front", False)
    done = filter_passes(g, requests, uniform, cache)
    del requests
    pixel_radiance, coverage = done.pop("radiance"), done.pop("coverage")
    covered = None
    for name, v in materials_px:
        if v.shape[1] == 1:  # one value per view: the mean over a pixel's covered
            if covered is None:  # sub-pixels is that value
                covered = (coverage > 0).to(v.dtype)
            done[name] = covered * v
    method_passes.clear()
    return pixel_radiance, coverage, {k: done[k] for k in order}


def _refine(entry, g, plan, radiance: torch.Tensor, passes: dict, args: tuple):
    """A supersampled plan's uniform pixels whose neighbourhood's radiances spread
    (:func:`torchrefract.geometry.adaptive.refine`) shaded at their other sub-pixels over
    the image so far: the plan without them, the radiance and the passes."""
    made = adaptive.refine(plan, radiance)
    if made is None:
        return plan, radiance, passes
    more, rest = made
    again = tiles.shade(entry, dataclasses.replace(g, shade=rest, canvas=radiance.view(-1, 3)),
                        *args)
    radiance, passes = adaptive.merge(radiance, passes, again, rest)
    return dataclasses.replace(plan, uniform=plan.uniform & ~more), radiance, passes


def _levels(entry, g, lattice, radiance: torch.Tensor, passes: dict, may_drive: bool,
            args: tuple) -> tuple[torch.Tensor, dict]:
    """After a first pass by the method's tensor code, each level of ``lattice``: its
    waiting pixels interpolated, or shaded over the image so far (``tiles.shade``). In
    csrc/lattice.c's driver (``fused.lattice_levels``, the fused methods' loop) where
    ``may_drive`` (no matte recording) and no gradient flows, else by adaptive.fill and
    adaptive.merge: the same values."""
    b, h, w = g.shape
    if may_drive and native.no_grad_through(radiance, *passes.values()):
        flat = radiance.view(-1, 3) if radiance.is_contiguous() else None

        def shade(idx: torch.Tensor) -> None:
            rest = torch.zeros(b * h * w, dtype=torch.bool)
            rest[idx] = True
            again = tiles.shade(entry, dataclasses.replace(
                g, shade=rest.view(b, h, w), canvas=flat, draw_in_place=True), *args)
            if again.radiance.data_ptr() != flat.data_ptr():  # (else drawn there)
                put_(flat, idx, take(again.radiance.reshape(-1, 3), idx))
            for k, v in passes.items():
                if k in again.passes:
                    c = v.shape[-1]
                    put_(v.view(-1, c), idx, take(again.passes[k].reshape(-1, c), idx))

        if flat is not None and fused.lattice_levels(lattice.levels, (b, h, w), radiance,
                                                     passes, shade):
            return radiance, passes
    for level in lattice.levels:  # interpolated, or shaded over the image so far
        radiance, passes, rest, soft = adaptive.fill(level, radiance, passes)
        if rest is None:
            continue
        again = tiles.shade(entry, dataclasses.replace(
            g, shade=rest, canvas=radiance.view(-1, 3)), *args)
        radiance, passes = adaptive.merge(radiance, passes, again, rest, soft)
    return radiance, passes


def finish_pass(scenes, entry, g, lighting, materials, options, state, budget, plan,
                 t_start: float) -> RenderResult:
    """The method's shading of a built G-buffer and the passes, on the tensors' device
    (``timings["shading"]``: from ``t_start``)."""
    method = entry.name
    extra = render_hook.requested(scenes)
    extra_passes: dict[str, torch.Tensor] = {}
    with collect() as stage_times, render_hook.scope(extra) as rec:
        lattice = plan.lattice if isinstance(plan, adaptive.Plan) else plan
        shaded = tiles.shade(entry, dataclasses.replace(g, lattice=lattice), lighting,
                             materials, options, state, budget)
        radiance, method_passes = shaded.radiance, shaded.passes
        if lattice is not None and adaptive.waiting(lattice.levels[0]):  # (else the fused
            # kernel ran every level: g.lattice) level by level, the waiting pixels
            radiance, method_passes = _levels(entry, g, lattice, radiance, method_passes,
                                              rec is None, (lighting, materials, options,
                                                            state, budget))
        if isinstance(plan, adaptive.Plan) and rec is None:  # pixels shaded once after all
            plan, radiance, method_passes = _refine(entry, g, plan, radiance, method_passes,
                                                    (lighting, materials, options, state,
                                                     budget))
        # never let NaN/Inf out, and never hide that it happened; a finite sum (one
        # reduction) proves every value finite, a non-finite one (or an overflow) is checked
        if not all_finite(radiance):
            bad = ~torch.isfinite(radiance)
            count = int(bad.any(-1).sum())
            warnings.warn(f"render ({method}): {count} sub-pixels had non-finite radiance and "
                          "were set to 0; please report the scene", RuntimeWarning,
                          stacklevel=2)
            radiance = torch.where(bad, torch.zeros_like(radiance), radiance)
        if rec is not None:  # every lookup's weight and sub-pixel, then the passes
            t_m = time.perf_counter()
            extra_passes = render_hook.make_passes(rec, radiance, box, g, scenes, extra)
            radiance = radiance.detach()
            method_passes = {k: v.detach() for k, v in method_passes.items()}
            stage_times["matte"] = time.perf_counter() - t_m
    if radiance.is_cuda:  # the shading's time, not its launches'
        torch.cuda.synchronize(radiance.device)
    t3 = time.perf_counter()

    # a supersampled plan's pixels shaded once hold their values at their first
    # sub-pixel: plan_box averages them as if copied to every sub-pixel
    uniform = plan.uniform if isinstance(plan, adaptive.Plan) else None
    pixel_radiance, coverage, passes = pixel_passes(g, radiance, method_passes, materials,
                                                    uniform)
    passes.update(extra_passes)  # already per pixel
    return RenderResult(
        radiance=pixel_radiance.float(),
        coverage=coverage[..., 0],
        passes=passes,
        scenes=tuple(s if s.method == method else s.replace(method=method) for s in scenes),
        timings={"shading": t3 - t_start,
                 "march": stage_times.get("march", 0.0), "mips": stage_times.get("mips", 0.0),
                 "fused": stage_times.get("fused", 0.0),
                 **({"matte": stage_times["matte"]} if "matte" in stage_times else {})},
    )


def merge(b: int, parts: list[tuple[list[int], RenderResult, list[float] | None]]
           ) -> RenderResult:
    """One RenderResult of B scenes from parts rendered apart: ``(idx, result, weights)``,
    the batch positions of the part's scenes, each image added to its position's with its
    weight (``auto``'s variants: a float, or an (H, W) map per pixel), or copied there with
    ``weights`` None (a large batch's
    chunks). A pass that only some parts have (another method's, or a part without object
    pixels) is zero elsewhere (it adds 0); the scenes are the last part's at each position;
    timings are summed."""
    first = parts[0][1]
    if (all(w is None for _, _, w in parts)
            and [i for idx, _, _ in parts for i in idx] == list(range(b))
            and all(r.passes.keys() == first.passes.keys() for _, r, _ in parts)):
        return _concatenated([r for _, r, _ in parts])  # a batch's chunks, in order
    dev = first.radiance.device
    radiance = torch.zeros((b, *first.radiance.shape[1:]), dtype=first.radiance.dtype,
                           device=dev)
    coverage = torch.zeros((b, *first.coverage.shape[1:]), dtype=first.coverage.dtype,
                           device=dev)
    passes: dict[str, torch.Tensor] = {}
    out_scenes: list[Scene | None] = [None] * b
    for idx, res, weights in parts:
        sel = torch.tensor(idx, device=dev)
        w = _weights(weights, len(idx), res.radiance.shape[1:3], dev)
        radiance.index_add_(0, sel, w * res.radiance)
        coverage[sel] = res.coverage  # the geometry's: the same for every variant
        for k, v in res.passes.items():
            if k not in passes:
                passes[k] = torch.zeros((b, *v.shape[1:]), dtype=v.dtype, device=dev)
            passes[k].index_add_(0, sel, w.to(v.dtype) * v)
        for j, i in enumerate(idx):
            out_scenes[i] = res.scenes[j]
    return RenderResult(radiance=radiance, coverage=coverage, passes=passes,
                        scenes=tuple(out_scenes),
                        timings=_summed_timings([r for _, r, _ in parts]))


def _weights(weights: list | None, n: int, size: tuple[int, int], dev) -> torch.Tensor:
    """A part's weights for :func:`merge`: (n, 1, 1, 1) from floats (0 + 1 * x is x exactly,
    so unweighted parts are copies), or (n, H, W, 1) where any is a per-pixel (H, W) map."""
    weights = weights or [1.0] * n
    if all(isinstance(w, float) for w in weights):
        return torch.tensor(weights, device=dev)[:, None, None, None]
    return torch.stack([torch.full(size, w) if isinstance(w, float) else w.to(torch.float32)
                        for w in weights]).to(dev)[..., None]


def _concatenated(results: list[RenderResult]) -> RenderResult:
    """:func:`merge` of unweighted parts that hold the batch's scenes in order: their images
    concatenated (the values the sums give, without zeroed buffers to add into)."""
    return RenderResult(
        radiance=torch.cat([r.radiance for r in results]),
        coverage=torch.cat([r.coverage for r in results]),
        passes={k: torch.cat([r.passes[k] for r in results]) for k in results[0].passes},
        scenes=tuple(s for r in results for s in r.scenes),
        timings=_summed_timings(results))


def _summed_timings(results: list[RenderResult]) -> dict[str, float]:
    """The parts' timings, each key summed over the parts that have it."""
    timings: dict[str, float] = {}
    for r in results:
        for k, v in r.timings.items():
            timings[k] = timings.get(k, 0.0) + v
    return timings


__all__ = ["MASKS", "BoxCache", "RenderResult", "all_finite", "box", "filter_passes",
           "finish_pass", "front_roughness", "geometry_requests", "mask_box", "masked_box",
           "merge", "pixel_passes", "plan_box"]
