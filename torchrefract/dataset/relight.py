"""Relight mode of a sweep (``relight: true``): a view rendered once, relit for every map.

Samples that differ only in their environment map (path, rotation, scale) share one
*relight group*: same mesh, transform, camera, material, lights, method, method options and
passes. The group's *source* is its lowest sample index in the whole sweep (so the plan
depends on the config alone, not on the batch size, the workers or what an earlier run
finished). A batch renders each of its groups' source scenes once with the environment
matte (:mod:`torchrefract.matte`, through the methods' tensor code) and writes:

- the source sample: that render (radiance, coverage, passes; the matte passes only where
  the scene asks for them), which is the direct tensor-code render bit for bit;
- every other sample of the group: :func:`torchrefract.relight` of the source's matte with
  the sample's map, rotation and scale, with the source's coverage and passes (they do not
  depend on the map), marked ``relit_from: <source sample id>`` in the manifest.

A relit image equals the direct tensor-code render to float32 rounding (<= 1e-6 relative
measured) where the matte folded or merged nothing; where it did (supersampled pixels with
more lookups than the matte's slots, ``internal_bounces: auto``) by more than
:data:`MAX_FOLDED` of a pixel's energy, the group's other samples are rendered directly
instead (and say so in their warnings). Methods without a matte (``auto``, ``reference``,
``lean``/``gsr`` with a box-MIP lookup) render every sample directly.
"""

from __future__ import annotations

import json
import time
from typing import Any

from torchrefract.scene.model import Scene

MAX_FOLDED = 1e-3
"""Largest fraction of a pixel's lobe energy the matte may fold or merge for relighting;
above it the group's samples are rendered directly."""

MAX_LOBES = 64
"""The matte's lobe slots for a relight render: 8 per sub-pixel (docs/matte.md, "How many
lobes": exact at 2x2 for every two-interface variant), at most this many."""


def relight_key(scene: Scene) -> str:
    """What a sample's image depends on besides its environment map (and its name and the
    PNG's exposure): samples with equal keys form one relight group."""
    d = scene.to_dict()
    for k in ("envmap", "name", "exposure"):
        d.pop(k, None)
    return json.dumps(d, sort_keys=True, separators=(",", ":"), default=str)


def sources(cfg, todo) -> dict[str, Any]:
    """Per sample id of ``todo``, the source :class:`~torchrefract.dataset.sweep.Sample` of
    its relight group: the group's lowest index in the whole sweep (samples whose scene is
    invalid belong to no group)."""
    from torchrefract.checks import ConfigError  # noqa: PLC0415

    keys = {relight_key(s.scene) for s in todo}
    first: dict[str, Any] = {}
    for i in range(cfg.num_samples):
        if len(first) == len(keys):
            break
        try:
            smp = cfg.sample(i)
        except ConfigError:
            continue
        k = relight_key(smp.scene)
        if k in keys and k not in first:
            first[k] = smp
    return {s.sample_id: first[relight_key(s.scene)] for s in todo}


def _matte_lobes(scene: Scene) -> int:
    """Lobe slots for the source's render: the scene's own matte pass if it asks for one
    (its passes are written as asked), else 8 per sub-pixel."""
    if "matte" in scene.passes:
        return int(scene.passes["matte"].get("lobes", 8))
    n = scene.camera.samples_per_pixel
    return min(MAX_LOBES, 8 * n * n)


def _strip(passes: dict, scene: Scene) -> dict:
    """The passes a direct render of ``scene`` gives: the matte's only where asked for."""
    if "matte" in scene.passes:
        return passes
    return {k: v for k, v in passes.items() if not k.startswith("matte.")}


def render_relit(items: list[tuple], settings=None) -> list[tuple[list[int], Any, list[str],
                                                                   str | None, dict]]:
    """Render a relight batch. ``items``: ``(index, sample_id, scene, source)`` with
    ``source`` the ``(index, sample_id, scene)`` of the item's group source.

    Returns groups as :func:`torchrefract.dataset.executors.render_items` builds them:
    ``(item positions, RenderResult or None, warnings, failure reason, extra)`` where
    ``extra`` holds per position the manifest's additions (``relit_from``) and the
    per-sample render time. Raises where the source render fails (the caller then renders
    the batch directly).
    """
    from torchrefract.dataset.attempt import failure_reason, render_batch  # noqa: PLC0415
    from torchrefract.matte.matte import from_passes  # noqa: PLC0415
    from torchrefract.matte.relight import prepare, relight  # noqa: PLC0415
    from torchrefract.result import RenderResult  # noqa: PLC0415

    order: dict[str, int] = {}
    src_scenes: list[Scene] = []
    for _, _, _, (_, ssid, sscene) in items:
        if ssid not in order:
            order[ssid] = len(src_scenes)
            src_scenes.append(sscene.replace(passes={**sscene.passes,
                                                     "matte": {"lobes": _matte_lobes(sscene)}}))
    t0 = time.perf_counter()
    res, warn = render_batch(src_scenes, settings)
    t_src = (time.perf_counter() - t0) / len(src_scenes)
    out = []
    direct: list[int] = []
    prepared: dict[int, Any] = {}  # per source: its prepared matte, or None (approximate)
    for k, (index, sid, scene, (_, ssid, _)) in enumerate(items):
        j = order[ssid]
        passes = {name: p[j:j + 1] for name, p in res.passes.items()}
        if sid == ssid:  # the source itself: its own render
            one = RenderResult(res.radiance[j:j + 1], res.coverage[j:j + 1],
                               _strip(passes, scene), (scene,), dict(res.timings))
            out.append(([k], one, warn, None, {"render_s": t_src}))
            continue
        if j not in prepared:
            m = from_passes(passes)
            exact = float((m.folded + m.merged).max()) <= MAX_FOLDED
            # the source's rotation: relit there op for op, elsewhere u shifted (cheaper)
            prepared[j] = prepare(m, src_scenes[j].envmap.rotate_deg) if exact else None
        if prepared[j] is None:
            direct.append(k)
            continue
        try:
            t1 = time.perf_counter()
            env = scene.envmap
            img = relight(prepared[j], env.path, env.rotate_deg, env.scale)
            t_rel = time.perf_counter() - t1
        except Exception as exc:  # noqa: BLE001 - a broken map fails its own sample
            out.append(([k], None, [], failure_reason(exc), {}))
            continue
        one = RenderResult(img, res.coverage[j:j + 1], _strip(passes, scene), (scene,),
                           {"relight": t_rel, "total": t_rel})
        out.append(([k], one, warn, None, {"render_s": t_rel, "relit_from": ssid}))
    for k in direct:  # the matte is approximate there: render these directly
        index, sid, scene, (_, ssid, _) = items[k]
        note = (f"relight: the matte of {ssid} folded or merged more than {MAX_FOLDED:g} "
                f"of a pixel's energy; rendered directly")
        try:
            r, w = render_batch([scene], settings)
            out.append(([k], r, w + [note], None, {}))
        except Exception as exc:  # noqa: BLE001
            out.append(([k], None, [], failure_reason(exc), {}))
    return out


__all__ = ["MAX_FOLDED", "MAX_LOBES", "relight_key", "render_relit", "sources"]
