"""The one data flow: scenes -> G-buffer (rasterized ids) -> method (torch) -> radiance and passes.

Example:
    >>> import torchrefract as tr
    >>> scenes = [tr.load_scene("configs/demo.yaml")]            # doctest: +SKIP
    >>> out = tr.render(scenes, method="specular")               # doctest: +SKIP
    >>> out.radiance.shape, out.coverage.shape                   # doctest: +SKIP
    (torch.Size([1, 256, 256, 3]), torch.Size([1, 256, 256]))
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from dataclasses import dataclass, field

import torch

from torchrefract import large, tiles
from torchrefract.checks import ConfigError
from torchrefract.geometry import adaptive
from torchrefract.geometry.camera import pixel_rays
from torchrefract.geometry.gbuffer import GBuffer, build_gbuffer
from torchrefract.geometry.mesh import load_mesh
from torchrefract.lighting.lights import Lighting
from torchrefract.matte import render_hook
from torchrefract.methods import registry
from torchrefract.optics.materials import MaterialBatch
from torchrefract.placement import on_device, to_device
from torchrefract.scene import Scene, validate
from torchrefract.settings import RenderSettings, current, using
from torchrefract.stages import collect


@dataclass(frozen=True)
class RenderResult:
    """Output of :func:`render` for B scenes at (H, W) pixels.

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


def _box(x: torch.Tensor, n: int) -> torch.Tensor:
    """Average n x n blocks of a (B, H, W, C) tensor -> (B, H/n, W/n, C).

    The sub-pixels are summed in row-major order and divided by n * n: the operations of
    ``F.avg_pool2d`` (the same bits, tests/test_box_filter.py), without its cost on this layout
    (8 x 512 x 512 x 1 floats, 2 threads: 1.0 ms against 6.0)."""
    if n == 1:
        return x
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


def _mask_box(mask: torch.Tensor, n: int, dtype: torch.dtype, cache: BoxCache | None
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, H, W, 1) ``mask`` as ``dtype``, and its box average."""
    key = (id(mask), dtype)
    if cache is not None and key in cache:
        return cache[key]
    m = mask[..., None].to(dtype)
    out = (m, _box(m, n))
    if cache is not None:
        cache[key] = out
    return out


def _masked_box(x: torch.Tensor, mask: torch.Tensor, n: int, cache: BoxCache | None = None
                ) -> torch.Tensor:
    """Average of x over the covered sub-pixels of each pixel (0 where none is covered)."""
    if n == 1:  # one sub-pixel per pixel: x where covered (x * 1 / 1 is x), else 0
        return torch.where(mask[..., None], x, torch.zeros((), dtype=x.dtype))
    m, den = _mask_box(mask, n, x.dtype, cache)
    num = _box(x * m, n)
    return torch.where(den > 0, num / den.clamp(min=1e-12), torch.zeros_like(num))


def _all_finite(x: torch.Tensor) -> bool:
    """Whether every value of ``x`` is finite: the sum of finite values is finite unless it
    overflows, where the elementwise test decides (NaN and Inf make the sum non-finite)."""
    with torch.no_grad():
        return bool(torch.isfinite(x.sum())) or bool(torch.isfinite(x).all())


def _geometry_passes(g: GBuffer, cache: BoxCache | None = None) -> dict[str, torch.Tensor]:
    n = g.supersample
    thick = (g.back.dist - g.front.dist).clamp(min=0.0)
    both = g.front.mask & g.back.mask
    if n == 1:  # a layer is zero where it is empty (gbuffer._layer): nothing to mask
        return {"depth_front": g.front.depth[..., None], "depth_back": g.back.depth[..., None],
                "normal_front": g.front.normal, "normal_back": g.back.normal,
                "thickness": _masked_box(thick[..., None], both, n, cache)}
    return {
        "depth_front": _masked_box(g.front.depth[..., None], g.front.mask, n, cache),
        "depth_back": _masked_box(g.back.depth[..., None], g.back.mask, n, cache),
        "normal_front": _masked_box(g.front.normal, g.front.mask, n, cache),
        "normal_back": _masked_box(g.back.normal, g.back.mask, n, cache),
        "thickness": _masked_box(thick[..., None], both, n, cache),
    }


def _front_roughness(g: GBuffer, materials: MaterialBatch) -> torch.Tensor:
    """The roughness at each front (sub-)pixel, (B, H, W), or (B, 1, 1) where no scene of
    the batch has a map (then it is each view's own)."""
    if not materials.has_maps:
        return materials.roughness[:, None, None]
    b, h, w = g.shape
    return materials.roughness_at(torch.arange(b).repeat_interleave(h * w),
                                  g.front.uv.reshape(-1, 2)).view(b, h, w)


def _check_batch(scenes: list[Scene]) -> None:
    c0 = scenes[0].camera
    for i, s in enumerate(scenes[1:], 1):
        c = s.camera
        if (c.width, c.height, c.samples_per_pixel) != (c0.width, c0.height,
                                                        c0.samples_per_pixel):
            raise ConfigError(
                f"render: scenes in one batch need the same camera.width, camera.height and "
                f"camera.samples_per_pixel; scene 0 ({scenes[0].name}) has "
                f"{c0.width}x{c0.height}@{c0.samples_per_pixel}, scene {i} ({s.name}) has "
                f"{c.width}x{c.height}@{c.samples_per_pixel}")
        if s.method_options != scenes[0].method_options:
            raise ConfigError(f"render: scenes in one batch need the same method_options; "
                              f"scene {i} ({s.name}) differs from scene 0")
        if s.passes != scenes[0].passes:
            raise ConfigError(f"render: scenes in one batch need the same passes; scene {i} "
                              f"({s.name}) asks for {sorted(s.passes)}, scene 0 "
                              f"({scenes[0].name}) for {sorted(scenes[0].passes)}")


def render(scenes: Scene | list[Scene], method: str | None = None,
           settings: RenderSettings | None = None) -> RenderResult:
    """Render scenes of one resolution in one batched tensor pass.

    Args:
        scenes: one Scene or a list of B scenes with equal camera width, height and
            samples_per_pixel, and equal ``method_options``.
        method: overrides every scene's ``method`` (default: the scenes' own, which must
            agree).
        settings: how the render runs (threads, kernels, compilation; default: the
            settings in force, else :meth:`RenderSettings.from_env`). Nothing it sets
            outlives the call, except heap reuse where asked for.

    Returns:
        RenderResult with (B, H, W, ...) tensors.

    Raises:
        ConfigError: mixed resolutions, methods or options; unknown method or option; a
            broken mesh or environment map (file and problem named); a view that does not
            fit the memory budget as one G-buffer (:mod:`torchrefract.tiles`) and that
            strips do not cover or fit either (before any work; :mod:`torchrefract.large`).
        NotImplementedError: a method of the design that is not implemented yet.
    """
    with using(settings):
        return _render(scenes, method)


def _render(scenes: Scene | list[Scene], method: str | None) -> RenderResult:
    if isinstance(scenes, Scene):
        scenes = [scenes]
    scenes = list(scenes)
    if not scenes:
        raise ConfigError("render: no scenes given")
    for s in scenes:
        if not isinstance(s, Scene):
            raise ConfigError(f"render: expected Scene objects, got {type(s).__name__}")
    if method is not None:  # the options are checked against the method that renders
        registry.get(method)  # an unknown name is a ConfigError before any work
    # Scenes built in Python get the same checks as loaded files (cheap: no file reads).
    scenes = [validate(s, method) for s in scenes]
    if method is None:
        methods = {s.method for s in scenes}
        if len(methods) > 1:
            raise ConfigError(f"render: scenes ask for different methods {sorted(methods)}; "
                              "pass method=... or render them separately")
        method = methods.pop()
    _check_batch(scenes)
    entry = registry.get(method)
    options = entry.parse(scenes[0].method_options, scenes[0].name)
    extra = render_hook.requested(scenes)  # ``matte`` / ``flow`` (torchrefract.matte)
    if registry.is_policy(method):
        if extra:
            raise ConfigError(f"render: passes {sorted(extra)} need a method, not the policy "
                              f"{method!r}; set method to one of "
                              f"{', '.join(render_hook.MATTE_METHODS)}")
        return _render_policy(scenes, entry, options)
    render_hook.check(method, extra, options)
    with render_hook.settings_for(extra):  # the tensor code, where lookups are recorded
        return _render_method(scenes, entry, options)


def _render_method(scenes: list[Scene], entry, options) -> RenderResult:
    budget = tiles.memory_budget()  # once: the passes' own memory must not shrink it
    if not tiles.fits_whole(scenes[0].camera, budget):  # a view larger than a G-buffer
        return large.render(scenes, entry, options, budget)
    parts = _chunks(scenes, budget)
    if len(parts) == 1:
        return _render_pass(scenes, entry, options, budget)
    start = 0
    placed = []
    for p in parts:
        placed.append((list(range(start, start + len(p))),
                       _render_pass(p, entry, options, budget), None))
        start += len(p)
    return _merge(len(scenes), placed)


MAX_PASS_SUBPIXELS = 1 << 19
"""Sub-pixels shaded in one tensor pass (8 views at 256x256). A larger batch is rendered in
consecutive chunks of views (the same pixels: a batch's images are those of its scenes
rendered alone): the march's per-sample plane lookups and the shading's gathers then stay
within a few views' buffers, and the peak memory follows the chunk, not the batch."""


def _chunks(scenes: list[Scene], budget: int | None = None) -> list[list[Scene]]:
    """The batch split into near-equal consecutive chunks of at most MAX_PASS_SUBPIXELS,
    and of at most the views one pass shades whole within the memory budget
    (:func:`torchrefract.tiles.views_per_pass`; a view that alone does not fit is a chunk of
    its own, shaded in tiles).

    Raises:
        ConfigError: one view does not fit the budget even in tiles (naming its size and
            the budget; :func:`torchrefract.tiles.check_view`).
    """
    c = scenes[0].camera
    per_view = c.width * c.height * c.samples_per_pixel ** 2
    budget = tiles.memory_budget() if budget is None else budget
    tiles.check_view(c, budget)
    most = max(1, min(MAX_PASS_SUBPIXELS // per_view, tiles.views_per_pass(c, budget)))
    n = -(-len(scenes) // most)  # chunks
    size = -(-len(scenes) // n)
    return [scenes[i:i + size] for i in range(0, len(scenes), size)]


def _render_pass(scenes: list[Scene], entry, options, budget: int) -> RenderResult:
    """One tensor pass over ``scenes`` (checked: one resolution, method and options), its
    shading in tiles where it does not fit ``budget`` bytes at once (:mod:`torchrefract.tiles`)."""

    method = entry.name
    t0 = time.perf_counter()
    state = entry.prepare(scenes, options)
    meshes = [load_mesh(s.mesh, s.transform) for s in scenes]
    lighting = Lighting.from_scenes(scenes)
    t1 = time.perf_counter()
    g = build_gbuffer(meshes, [s.camera for s in scenes])
    materials = MaterialBatch.from_scenes(scenes)
    plan = None
    if current().adaptive and entry.shades_object_index:
        if g.supersample > 1:
            g, plan = adaptive.plan(g, torch.stack([pixel_rays(s.camera) for s in scenes]),
                                    _front_roughness(g, materials))
        else:
            g, plan = adaptive.lattice(g, _front_roughness(g, materials))
    want = current().torch_device()
    # a CPU-only method shades on the CPU; its result is moved at the end
    device = want if want.type in entry.devices else torch.device("cpu")
    if device.type != "cpu":
        g, lighting, materials, plan = to_device((g, lighting, materials, plan), device)
    t2 = time.perf_counter()
    with on_device(device):
        result = _finish_pass(scenes, entry, g, lighting, materials, options, state, budget,
                              plan, t2)
    result.timings.update({"load": t1 - t0, "gbuffer": t2 - t1,
                           "total": time.perf_counter() - t0})
    return result if want == device else to_device(result, want)


def _finish_pass(scenes, entry, g, lighting, materials, options, state, budget, plan,
                 t_start: float) -> RenderResult:
    """The method's shading of a built G-buffer and the passes, on the tensors' device
    (``timings["shading"]``: from ``t_start``)."""
    method = entry.name
    n = g.supersample
    extra = render_hook.requested(scenes)
    extra_passes: dict[str, torch.Tensor] = {}
    with collect() as stage_times, render_hook.scope(extra) as rec:
        shaded = tiles.shade(entry, g, lighting, materials, options, state, budget)
        radiance, method_passes = shaded.radiance, shaded.passes
        if isinstance(plan, adaptive.Plan):  # the pixels shaded once: to every sub-pixel
            radiance, method_passes = adaptive.spread(plan, radiance, method_passes)
        elif isinstance(plan, adaptive.Lattice):  # level by level, the waiting pixels:
            for level in plan.levels:  # interpolated, or shaded over the image so far
                radiance, method_passes, rest, soft = adaptive.fill(level, radiance,
                                                                    method_passes)
                if rest is None:
                    continue
                again = tiles.shade(entry, dataclasses.replace(
                    g, shade=rest, canvas=radiance.view(-1, 3)), lighting, materials,
                    options, state, budget)
                radiance, method_passes = adaptive.merge(radiance, method_passes, again,
                                                         rest, soft)
        # never let NaN/Inf out, and never hide that it happened; a finite sum (one
        # reduction) proves every value finite, a non-finite one (or an overflow) is checked
        if not _all_finite(radiance):
            bad = ~torch.isfinite(radiance)
            count = int(bad.any(-1).sum())
            warnings.warn(f"render ({method}): {count} sub-pixels had non-finite radiance and "
                          "were set to 0; please report the scene", RuntimeWarning,
                          stacklevel=2)
            radiance = torch.where(bad, torch.zeros_like(radiance), radiance)
        if rec is not None:  # every lookup's weight and sub-pixel, then the passes
            t_m = time.perf_counter()
            extra_passes = render_hook.make_passes(rec, radiance, _box, g, scenes, extra)
            radiance = radiance.detach()
            method_passes = {k: v.detach() for k, v in method_passes.items()}
            stage_times["matte"] = time.perf_counter() - t_m
    if radiance.is_cuda:  # the shading's time, not its launches'
        torch.cuda.synchronize(radiance.device)
    t3 = time.perf_counter()

    cache: BoxCache = {}  # the masks' box averages, computed once for all passes
    passes = _geometry_passes(g, cache)
    # Material passes (per object pixel): what a model trained on the data may regress.
    fm = _mask_box(g.front.mask, n, torch.float32, cache)[0]  # (B, H, W, 1)
    rough = _front_roughness(g, materials)[..., None]
    for name, v in (("roughness", fm * rough), ("ior", fm * materials.ior[:, None, None, None])):
        passes[name] = v if n == 1 else _masked_box(v, g.front.mask, n, cache)  # 0 outside
    for k, v in method_passes.items():
        passes[k] = _masked_box(v, g.front.mask, n, cache)
    passes.update(extra_passes)  # already per pixel
    return RenderResult(
        radiance=_box(radiance, n).float(),
        coverage=_mask_box(g.front.mask, n, torch.float32, cache)[1][..., 0],
        passes=passes,
        scenes=tuple(s if s.method == method else s.replace(method=method) for s in scenes),
        timings={"shading": t3 - t_start,
                 "march": stage_times.get("march", 0.0), "mips": stage_times.get("mips", 0.0),
                 "fused": stage_times.get("fused", 0.0),
                 **({"matte": stage_times["matte"]} if "matte" in stage_times else {})},
    )


def _render_policy(scenes: list[Scene], policy, options) -> RenderResult:
    """A policy (``auto``): the variants of each scene (:meth:`resolve`: one, or a weighted
    blend near the choice's thresholds), the scenes that share a variant rendered together,
    and each scene's images summed with their weights in batch order. The result's scenes
    carry the picked method and options (a blend's: the policy's scene); ``blends`` every
    variant and weight."""
    t0 = time.perf_counter()
    picked = policy.resolve(scenes, options)
    groups: dict[tuple[str, str], list[tuple[int, float]]] = {}
    for i, c in enumerate(picked):
        for method, opts, w in c.blend:
            groups.setdefault((method, json.dumps(opts, sort_keys=True)), []).append((i, w))
    parts = []
    for (method, opts), members in groups.items():
        idx = [i for i, _ in members]
        sub = [scenes[i].replace(method=method, method_options=json.loads(opts)) for i in idx]
        parts.append((idx, _render(sub, None), [w for _, w in members]))
    out = _merge(len(scenes), parts)
    out.timings["total"] = time.perf_counter() - t0
    # A single pick is recorded as the scene (re-rendering it gives the same image); a blend
    # keeps the policy's scene (re-rendering it with the same table gives the same image).
    return dataclasses.replace(
        out, scenes=tuple(scenes[i].replace(method=c.method, method_options=c.options)
                          if len(c.blend) == 1 else scenes[i] for i, c in enumerate(picked)),
        blends=tuple(c.blend for c in picked), predictions=tuple(c.record() for c in picked))


def _merge(b: int, parts: list[tuple[list[int], RenderResult, list[float] | None]]
           ) -> RenderResult:
    """One RenderResult of B scenes from parts rendered apart: ``(idx, result, weights)``,
    the batch positions of the part's scenes, each image added to its position's with its
    weight (``auto``'s variants), or copied there with ``weights`` None (a large batch's
    chunks). A pass that only some parts have (another method's, or a part without object
    pixels) is zero elsewhere (it adds 0); the scenes are the last part's at each position;
    timings are summed."""
    first = parts[0][1]
    dev = first.radiance.device
    radiance = torch.zeros((b, *first.radiance.shape[1:]), dtype=first.radiance.dtype,
                           device=dev)
    coverage = torch.zeros((b, *first.coverage.shape[1:]), dtype=first.coverage.dtype,
                           device=dev)
    passes: dict[str, torch.Tensor] = {}
    out_scenes: list[Scene | None] = [None] * b
    timings: dict[str, float] = {}
    for idx, res, weights in parts:
        sel = torch.tensor(idx, device=dev)
        # (n, 1, 1, 1) weights; 0 + 1 * x is x exactly, so unweighted parts are copies
        w = torch.tensor(weights or [1.0] * len(idx), device=dev)[:, None, None, None]
        radiance.index_add_(0, sel, w * res.radiance)
        coverage[sel] = res.coverage  # the geometry's: the same for every variant
        for k, v in res.passes.items():
            if k not in passes:
                passes[k] = torch.zeros((b, *v.shape[1:]), dtype=v.dtype, device=dev)
            passes[k].index_add_(0, sel, w.to(v.dtype) * v)
        for j, i in enumerate(idx):
            out_scenes[i] = res.scenes[j]
        for k, v in res.timings.items():
            timings[k] = timings.get(k, 0.0) + v
    return RenderResult(radiance=radiance, coverage=coverage, passes=passes,
                        scenes=tuple(out_scenes), timings=timings)
