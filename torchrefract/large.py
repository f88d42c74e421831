"""Frames too large for one G-buffer, in bounded memory: strips of rows over the frame's
marched layers (issue #27).

A view whose G-buffer does not fit the memory budget even with its shading in tiles
(:func:`torchrefract.tiles.fits_whole`) is rendered here, one view at a time:

1. the back layer's triangle ids of the whole frame (4 bytes per sub-pixel; with internal
   bounces the front layer's too), strip by strip: each strip's ids rasterized
   (``native_layers`` with ``rows``) and made exact (the G-buffer's edge repair, with one
   row above and below so that it sees the neighbours it sees in the whole frame), only
   the ids kept; with each view's triangle planes they are what the march reads
   (:class:`torchrefract.kernels.march.Marched`);
2. per strip of whole pixel rows: the strip's rays and exact layers again, a G-buffer of
   the strip whose ``marched`` is the whole frame's, shaded and box-filtered as a whole
   G-buffer is (``result.finish_pass``), its pixels copied into the output.

Every sub-pixel gets the values of the untiled render, bit for bit: rays, ids and layers
are per sub-pixel (the repair's 3x3 neighbourhood included), the march reads the frame's
ids and planes, shading and the passes are per (sub-)pixel, and strips hold whole pixels
(tests/test_large.py). What it needs: the ids (4 bytes per sub-pixel and marched layer),
the output (:data:`OUT_BYTES` per pixel) and one strip (:data:`STRIP_BYTES` per sub-pixel);
a view for which even one pixel row does not fit fails up front, naming its size and the
budget.

Scope: the fused kernels of ``rousiers`` (default cone and spread), ``specular``,
``prefiltered`` and ``sh`` on the CPU, uniform roughness (``sh``: a roughness map too, read
at each pixel's front hit), no extra passes (``matte``, ``flow``): elsewhere a method's
tensor code reads the back layer's mips or the frame's pixels outside the strip. Those
views keep the up-front error. A frame in strips shades every pixel, whatever
``RenderSettings.adaptive`` says (the lattice's neighbours and levels would cross the
strips' edges).
"""

from __future__ import annotations

import time

import torch

from torchrefract import tiles
from torchrefract.checks import ConfigError
from torchrefract.geometry.camera import views_pixel_rays
from torchrefract.geometry.gbuffer import GBuffer, Layer, MeshBatch, _layer, view_frames
from torchrefract.geometry.mesh import load_mesh
from torchrefract.geometry.raster import native_layers
from torchrefract.kernels import native
from torchrefract.kernels.march import Marched, plane_table
from torchrefract.lighting.lights import Lighting
from torchrefract.methods import registry
from torchrefract.optics.materials import MaterialBatch
from torchrefract.result import RenderResult, finish_pass, merge
from torchrefract.scene import Camera, Scene
from torchrefract.settings import current


def has_strips(entry) -> bool:
    """Whether a method says when its fused kernel renders in strips (it has its own
    :meth:`~torchrefract.methods.base.Method.strips`)."""
    from torchrefract.methods.base import Method  # noqa: PLC0415 (the loader imports here)

    return type(entry).strips is not Method.strips


def strip_methods() -> list[str]:
    """The methods a frame too large for one G-buffer renders with (every registered one
    imported: for an error's text)."""
    return [n for n in registry.method_names()
            if n not in registry.POLICIES and has_strips(registry.get(n))]

MARCHED_BYTES = 4
"""Bytes per sub-pixel and marched layer held for the whole frame (an int32 id)."""
OUT_BYTES = 96
"""Bytes per output pixel: radiance, coverage and up to 20 pass channels, float32."""
STRIP_BYTES = 384
"""Bytes per sub-pixel of a strip (its G-buffer, rays, ids, radiance and passes before
the box filter, the fused kernels' outputs): 243 measured (``rousiers``, 1024x1024 at 4x4
samples, 56% object; docs/benchmarks.md, "Large frames"), with room for internal
bounces' passes and a frame the object fills."""


def why_not(scenes: list[Scene], entry, options) -> str | None:
    """Why these scenes cannot be rendered in strips (None: they can; module docstring):
    the render's settings and the scenes' extras here, the method's own limits from
    :meth:`~torchrefract.methods.base.Method.strips`."""
    s = current()
    if not has_strips(entry):
        return f"method {entry.name!r} (strips: {', '.join(strip_methods())} only)"
    if not (s.fused and native.available()):
        return "the fused kernels are off or unavailable (strips need them)"
    if s.torch_device().type != "cpu":
        return "strips run on the CPU"
    if any(len(sc.lights) > 64 for sc in scenes):
        return "more than 64 lights"
    if any(sc.passes for sc in scenes):
        return "extra passes (matte, flow)"
    return entry.strips(scenes, options)


def fixed_bytes(camera: Camera, both: bool, views: int = 1) -> int:
    """What a view in strips holds whatever the strips: the pass's fixed part, the marched
    ids and the output (of all ``views`` of the batch: the result holds them together)."""
    n = camera.samples_per_pixel
    sub = camera.width * camera.height * n * n
    return (tiles.PASS_BYTES_FIXED + MARCHED_BYTES * (2 if both else 1) * sub
            + OUT_BYTES * camera.width * camera.height * views)


def strip_rows(camera: Camera, budget: int, both: bool, views: int = 1) -> int:
    """Sub-pixel rows per strip within ``budget`` (a multiple of samples_per_pixel), or 0
    where not even one pixel row fits."""
    n = camera.samples_per_pixel
    room = budget - fixed_bytes(camera, both, views)
    rows = room // (STRIP_BYTES * camera.width * n) if room > 0 else 0
    return int(min(rows - rows % n, camera.height * n))


def check(scenes: list[Scene], entry, options, budget: int) -> int:
    """Sub-pixel rows per strip for these scenes' views; ConfigError, before any work,
    where they cannot be rendered in strips or one pixel row does not fit ``budget``."""
    c = scenes[0].camera
    per_view = c.width * c.height * c.samples_per_pixel ** 2
    head = (f"render: one {c.width}x{c.height} view at samples_per_pixel "
            f"{c.samples_per_pixel} ({per_view:,} sub-pixels)")
    whole = tiles.size_text(tiles.pass_bytes(per_view, min(per_view, tiles.MIN_TILE)),
                            up=True)
    tail = (f"the memory budget of {tiles.size_text(budget)} (RenderSettings.memory_budget_mb, "
            f"TORCHREFRACT_MEMORY_MB; default: 80% of the available memory)")
    reason = why_not(scenes, entry, options)
    if reason is not None:
        raise ConfigError(
            f"{head} needs about {whole} as one G-buffer, over {tail}; a frame this large "
            f"renders in strips only with the fused kernels of {', '.join(strip_methods())}, not "
            f"here: {reason}. Render it smaller, with fewer samples per pixel or with one "
            f"of those methods on the fused kernels")
    both = entry.marches_front(options)
    views = len(scenes)
    rows = strip_rows(c, budget, both, views)
    if rows < c.samples_per_pixel:
        need = fixed_bytes(c, both, views) + STRIP_BYTES * c.width * c.samples_per_pixel ** 2
        alone = ("fits" if strip_rows(c, budget, both) >= c.samples_per_pixel
                 else "does not fit either")
        batch = (f" in a batch of {views} (their outputs held together; one alone: {alone})"
                 if views > 1 else "")
        raise ConfigError(
            f"{head}{batch} needs about {tiles.size_text(need, up=True)} even in strips of "
            f"one pixel row (its marched layers' ids, {MARCHED_BYTES} bytes per sub-pixel "
            f"and layer, and the output, {OUT_BYTES} bytes per pixel, held whole), over "
            f"{tail}: render it smaller, with fewer samples per pixel"
            f"{' or in smaller batches' if views > 1 else ''}")
    return rows


def _strip_layers(mesh, cam: Camera, n: int, batch: MeshBatch, eye, fwd, r0: int, r1: int,
                  front: bool, back: bool):
    """The exact layers (front, back; None where not asked for) and rays of the frame's
    sub-pixel rows [r0, r1): drawn and made exact with one row more on each side (the edge
    repair's neighbourhood), then cut to the strip."""
    h = cam.height * n
    a, b = max(0, r0 - 1), min(h, r1 + 1)
    ids = native_layers([mesh], [cam], n, [0], rows=(a, b))
    if ids is None:
        raise RuntimeError("the native rasterizer could not run (strips need it)")
    dirs = views_pixel_rays([cam], n, rows=(a, b))  # (1, b - a, W, 3)
    cut = slice(r0 - a, r1 - a)

    def exact(i: int, is_back: bool) -> Layer:
        lay = _layer(ids[i], eye, dirs, fwd, batch, back=is_back)
        return Layer(**{k: None if v is None else v[:, cut] for k, v in vars(lay).items()})

    out = (exact(0, False) if front else None, exact(1, True) if back else None)
    del ids
    return out, dirs[:, cut]


def marched_layers(mesh, cam: Camera, batch: MeshBatch, eye, fwd, proj, both: bool,
                   rows: int) -> Marched:
    """The whole frame's :class:`Marched` layers, built strip by strip (``rows`` sub-pixel
    rows each): the exact back layer's ids (``both``: the front's too), int32."""
    n = cam.samples_per_pixel
    h, w = cam.height * n, cam.width * n
    back = torch.empty(h * w, dtype=torch.int32)
    front = torch.empty(h * w, dtype=torch.int32) if both else None
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        (fl, bl), _ = _strip_layers(mesh, cam, n, batch, eye, fwd, r0, r1, both, True)
        back[r0 * w:r1 * w] = bl.tri.reshape(-1)
        if both:
            front[r0 * w:r1 * w] = fl.tri.reshape(-1)
        del fl, bl
    table, base = plane_table(batch, eye, proj)
    return Marched(back=back, front=front, table=table, base=base, h=h, w=w)


def render(scenes: list[Scene], entry, options, budget: int, rows: int | None = None):
    """Render each of ``scenes`` in strips (module docstring): a ``RenderResult`` of the
    batch, the views one after another. ``rows``: sub-pixel rows per strip (default: as
    many as ``budget`` allows; a multiple of samples_per_pixel).

    Raises:
        ConfigError: the views cannot be rendered in strips or do not fit ``budget`` even
            in strips of one pixel row (before any work; :func:`check`).
    """
    fit = check(scenes, entry, options, budget)
    n = scenes[0].camera.samples_per_pixel
    if rows is None:
        rows = fit
    elif rows < 1 or rows % n:
        raise ConfigError(f"render: strips of {rows} sub-pixel rows: expected a positive "
                          f"multiple of samples_per_pixel {n}")
    parts = [([i], _render_view(s, entry, options, budget, rows), None)
             for i, s in enumerate(scenes)]
    return parts[0][1] if len(parts) == 1 else merge(len(scenes), parts)


def _render_view(scene: Scene, entry, options, budget: int, rows: int):
    t0 = time.perf_counter()
    cam, n = scene.camera, scene.camera.samples_per_pixel
    both = entry.marches_front(options)
    state = entry.prepare([scene], options)
    mesh = load_mesh(scene.mesh, scene.transform)
    lighting = Lighting.from_scenes([scene])
    materials = MaterialBatch.from_scenes([scene])
    t1 = time.perf_counter()
    batch = MeshBatch.from_meshes([mesh])
    eye, fwd, proj = view_frames([cam], n)  # one view, as build_gbuffer's
    marched = marched_layers(mesh, cam, batch, eye, fwd, proj, both, rows)
    t2 = time.perf_counter()
    # the strip's shading is the fused kernels', which need next to nothing per shaded
    # sub-pixel (STRIP_BYTES has it): no tiles inside a strip (each would repeat the
    # strip's background)
    strip_budget = 1 << 62
    out = None
    timings: dict[str, float] = {}
    h = cam.height * n
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        t_g = time.perf_counter()
        (front, back), dirs = _strip_layers(mesh, cam, n, batch, eye, fwd, r0, r1, True,
                                            True)
        timings["gbuffer"] = timings.get("gbuffer", 0.0) + time.perf_counter() - t_g
        g = GBuffer(front=front, back=back, ray_dir=dirs, eye=eye, proj=proj, meshes=batch,
                    supersample=n, marched=marched)
        part = finish_pass([scene], entry, g, lighting, materials, options, state,
                            strip_budget, None, time.perf_counter())
        del g, front, back, dirs
        if out is None:  # the output, whole: each strip's pixel rows copied in
            def full(x: torch.Tensor) -> torch.Tensor:
                return torch.zeros((1, cam.height) + tuple(x.shape[2:]), dtype=x.dtype)

            out = RenderResult(radiance=full(part.radiance), coverage=full(part.coverage),
                               passes={k: full(v) for k, v in part.passes.items()},
                               scenes=part.scenes)
        y0, y1 = r0 // n, r1 // n
        out.radiance[:, y0:y1] = part.radiance
        out.coverage[:, y0:y1] = part.coverage
        for k, v in part.passes.items():
            if k not in out.passes:  # a pass an earlier strip lacked: zero there
                out.passes[k] = torch.zeros((1, cam.height) + tuple(v.shape[2:]),
                                            dtype=v.dtype)
            out.passes[k][:, y0:y1] = v
        for k, v in part.timings.items():
            timings[k] = timings.get(k, 0.0) + v
        del part
    timings.update(load=t1 - t0, gbuffer=timings.get("gbuffer", 0.0) + t2 - t1,
                   total=time.perf_counter() - t0)
    out.timings.update(timings)
    return out


__all__ = ["MARCHED_BYTES", "OUT_BYTES", "STRIP_BYTES", "check", "fixed_bytes", "has_strips",
           "marched_layers", "render", "strip_methods", "strip_rows", "why_not"]
