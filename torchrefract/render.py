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
import math
import time
import warnings

import torch

from torchrefract import large, sparse, tiles
from torchrefract.checks import ConfigError
from torchrefract.geometry import adaptive
from torchrefract.geometry.camera import views_pixel_rays
from torchrefract.geometry.gbuffer import build_gbuffer
from torchrefract.geometry.mesh import load_mesh
from torchrefract.lighting.lights import Lighting
from torchrefract.matte import render_hook
from torchrefract.methods import registry
from torchrefract.optics.materials import MaterialBatch
from torchrefract.placement import on_device, to_device
from torchrefract.result import RenderResult, finish_pass, front_roughness
from torchrefract.result import merge as merge_parts
from torchrefract.scene import Scene, validate
from torchrefract.settings import RenderSettings, current, using


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


def _render(scenes: Scene | list[Scene], method: str | None,
            regions: list[torch.Tensor | None] | None = None) -> RenderResult:
    """:func:`render` in the settings in force; ``regions`` (a policy's variants, per scene:
    (height, width) bool or None): the object pixels a method shades
    (:func:`_render_method`)."""
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
        return _render_method(scenes, entry, options, regions)


def _render_method(scenes: list[Scene], entry, options,
                   regions: list[torch.Tensor | None] | None = None) -> RenderResult:
    """A method's render of the batch, in chunks where it is large. ``regions``: per scene
    the (height, width) bool pixels whose object sub-pixels are shaded (None: all); the
    others' radiance is what the background leaves there and their method passes are 0.
    The same pixels inside a region as the whole render's, except where adaptive shading
    would have interpolated them from pixels outside it (shaded instead). A view shaded in
    strips (:mod:`torchrefract.large`) is shaded whole."""
    budget = tiles.memory_budget()  # once: the passes' own memory must not shrink it
    if not tiles.fits_whole(scenes[0].camera, budget):  # a view larger than a G-buffer
        return large.render(scenes, entry, options, budget)
    if regions is not None and all(r is None for r in regions):
        regions = None
    split = _sparse_split(scenes, entry, options)
    if split is not None:  # each view as it renders alone
        return merge_parts(len(scenes), [(idx, _render_method(
            [scenes[i] for i in idx], entry, options,
            None if regions is None else [regions[i] for i in idx]), None) for idx in split])
    parts = _chunks(scenes, budget)
    if len(parts) == 1:
        return _render_pass(scenes, entry, options, budget, regions)
    start = 0
    placed = []
    for p in parts:
        sub = None if regions is None else regions[start:start + len(p)]
        placed.append((list(range(start, start + len(p))),
                       _render_pass(p, entry, options, budget, sub), None))
        start += len(p)
    return merge_parts(len(scenes), placed)


def _sparse_split(scenes: list[Scene], entry, options) -> list[list[int]] | None:
    """Where some views of a supersampled batch would take sparse supersampling alone and
    the batch as a whole does not (``lean`` beside a view with a roughness map): the
    views' indices in groups that each render as their views do alone; else None."""
    if (len(scenes) < 2 or scenes[0].camera.samples_per_pixel < 2 or not current().adaptive
            or sparse.applies(scenes, entry, options, MaterialBatch.from_scenes(scenes))):
        return None
    alone = [sparse.applies([s], entry, options, MaterialBatch.from_scenes([s]))
             for s in scenes]
    if not any(alone):
        return None
    if all(alone):  # (a batch-wide condition none of them has alone: each by itself)
        return [[i] for i in range(len(scenes))]
    return [[i for i, a in enumerate(alone) if a], [i for i, a in enumerate(alone) if not a]]


MAX_PASS_SUBPIXELS = 1 << 21
"""Sub-pixels shaded in one pass (8 views at 256x256 with 2x2 samples, or at 512x512). A
larger batch is rendered in consecutive chunks of views (the same pixels: a batch's images
are those of its scenes rendered alone), so the peak memory follows the chunk, not the
batch; a pass's fixed cost (set-up, kernel calls) is paid once per chunk (measured:
docs/decisions.md, "Chunked passes and shared views")."""


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


def _render_pass(scenes: list[Scene], entry, options, budget: int,
                 regions: list[torch.Tensor | None] | None = None) -> RenderResult:
    """One tensor pass over ``scenes`` (checked: one resolution, method and options), its
    shading in tiles where it does not fit ``budget`` bytes at once (:mod:`torchrefract.tiles`);
    ``regions``: :func:`_render_method`'s."""

    t0 = time.perf_counter()
    state = entry.prepare(scenes, options)
    meshes = [load_mesh(s.mesh, s.transform) for s in scenes]
    lighting = Lighting.from_scenes(scenes)
    t1 = time.perf_counter()
    materials = MaterialBatch.from_scenes(scenes)
    sparse_pass = sparse.applies(scenes, entry, options, materials)
    if sparse_pass:  # the one-sample G-buffer and the ids at n x n
        g, ids, flags = sparse.gbuffer(meshes, [s.camera for s in scenes])
    else:
        g = build_gbuffer(meshes, [s.camera for s in scenes])
    _warn_inside(scenes, meshes, g)
    region = _subpixel_region(regions, g) if entry.shades_object_index else None
    plan = None
    pending = None
    if sparse_pass:  # the one-sample pass, then the pixels whose samples can differ
        g, plan, pending = sparse.first_pass(g, ids, flags, materials, region)
    elif current().adaptive and entry.shades_object_index:
        if g.supersample > 1:
            alpha = front_roughness(g, materials)
            g, plan = adaptive.plan(g, views_pixel_rays([s.camera for s in scenes]),
                                    alpha, region=region)
            g, centers = adaptive.lattice(g, alpha, uniform=plan.uniform, region=region)
            plan = dataclasses.replace(plan, lattice=centers)
        else:
            g, plan = adaptive.lattice(g, front_roughness(g, materials), region=region)
    elif region is not None:
        g = dataclasses.replace(g, shade=g.front.mask & region)
    want = current().torch_device()
    # a CPU-only method shades on the CPU; its result is moved at the end
    device = want if want.type in entry.devices else torch.device("cpu")
    if device.type != "cpu":
        g, lighting, materials, plan = to_device((g, lighting, materials, plan), device)
    t2 = time.perf_counter()
    with on_device(device):
        result = finish_pass(scenes, entry, g, lighting, materials, options, state, budget,
                              plan, t2)
        if pending is not None:
            result = sparse.supersample(result, pending, scenes, entry, lighting, materials,
                                        options, state, budget)
    result.timings.update({"load": t1 - t0, "gbuffer": t2 - t1 + result.timings.get(
        "gbuffer", 0.0), "total": time.perf_counter() - t0})
    return result if want == device else to_device(result, want)


def _warn_inside(scenes: list[Scene], meshes, g) -> None:
    """Warn of a view whose camera sits inside its mesh's bounding sphere and sees none of
    the mesh: from inside the glass the two layers show nothing, the image is the
    environment alone (a sweep's orbit too close, a scale too large)."""
    for i, (s, m) in enumerate(zip(scenes, meshes)):
        c, r = m.bounding_sphere()
        if math.dist(s.camera.eye, c) < r and not bool(g.front.mask[i].any()):
            warnings.warn(f"render: scene {s.name!r}: the camera at {tuple(s.camera.eye)} is "
                          f"inside the mesh's bounds and sees none of it (from inside the "
                          f"glass the image is the environment alone)", stacklevel=4)


def _subpixel_region(regions: list[torch.Tensor | None] | None, g) -> torch.Tensor | None:
    """(B, H, W) bool over ``g``'s sub-pixels: each view's (height, width) region repeated
    over its sub-pixels, True everywhere for a view without one; None without regions."""
    if regions is None:
        return None
    b, h, w = g.shape
    n = g.supersample
    out = torch.ones((b, h, w), dtype=torch.bool)
    for i, r in enumerate(regions):
        if r is not None:
            if tuple(r.shape) != (h // n, w // n):
                raise ValueError(f"render: region of view {i} is {tuple(r.shape)}, the view "
                                 f"{(h // n, w // n)}")
            out[i] = r.to(torch.bool).repeat_interleave(n, 0).repeat_interleave(n, 1)
    return out


def _render_policy(scenes: list[Scene], policy, options) -> RenderResult:
    """A policy (``auto``): the variants of each scene (:meth:`resolve`: one, or a weighted
    blend near the choice's thresholds), the scenes that share a variant rendered together,
    and each scene's images summed with their weights in batch order. The result's scenes
    carry the picked method and options (a blend's: the policy's scene); ``blends`` every
    variant and weight. A choice with per-pixel weights (``maps``) renders each variant
    only on the pixels where it weighs (:func:`_render_method`'s regions) and adds the
    images with those weights."""
    t0 = time.perf_counter()
    picked = policy.resolve(scenes, options)
    groups: dict[tuple[str, str], list[tuple[int, object]]] = {}
    for i, c in enumerate(picked):
        for k, (method, opts, w) in enumerate(c.blend):
            weight = w if getattr(c, "maps", None) is None else c.maps[k]
            if not isinstance(weight, float) and not bool((weight > 0).any()):
                continue  # weighs nowhere: nothing to add
            groups.setdefault((method, json.dumps(opts, sort_keys=True)), []).append(
                (i, weight))
    parts = []
    for (method, opts), members in groups.items():
        idx = [i for i, _ in members]
        sub = [scenes[i].replace(method=method, method_options=json.loads(opts)) for i in idx]
        regions = [None if isinstance(w, float) else w > 0 for _, w in members]
        parts.append((idx, _render(sub, None, regions), [w for _, w in members]))
    out = merge_parts(len(scenes), parts)
    out.timings["total"] = time.perf_counter() - t0
    # A single pick is recorded as the scene (re-rendering it gives the same image); a blend
    # keeps the policy's scene (re-rendering it with the same table gives the same image).
    return dataclasses.replace(
        out, scenes=tuple(scenes[i].replace(method=c.method, method_options=c.options)
                          if len(c.blend) == 1 else scenes[i] for i, c in enumerate(picked)),
        blends=tuple(c.blend for c in picked), predictions=tuple(c.record() for c in picked))


