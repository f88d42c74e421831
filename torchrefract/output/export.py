"""Writers: one render -> ``<name>.exr`` (R, G, B, A + passes), ``<name>.png``, ``<name>.json``.

EXR channels: ``R, G, B`` linear radiance (background included), ``A`` object coverage,
then each pass: one-channel passes under their own name (``depth_front``), three-channel
passes as ``<pass>.X``, ``.Y``, ``.Z``. The JSON records how the image was made (resolved
scene, method, package version, torch threads, timings). All writes are atomic.
"""

from __future__ import annotations

import json
import platform
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Sequence, TypeVar

import numpy as np
import torch

from torchrefract.output.atomic import write_text
from torchrefract.output.images import write_exr, write_png
from torchrefract.result import RenderResult

_AXES = ("X", "Y", "Z", "W")
_T, _R = TypeVar("_T"), TypeVar("_R")


def in_threads(fn: Callable[[_T], _R], items: Sequence[_T], name: str) -> list[_R]:
    """``fn`` of each item, in order, in as many threads (named ``name``) as torch has:
    encoding files (zlib, OpenEXR, hashlib) lets go of the GIL, so a batch's frames encode
    side by side; one at a time in this thread where one thread would do."""
    threads = min(len(items), torch.get_num_threads())
    if threads <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(threads, thread_name_prefix=name) as pool:
        return list(pool.map(fn, items))


def exr_channels(result: RenderResult, i: int) -> dict[str, np.ndarray]:
    """The EXR channels of scene ``i`` of a result: name -> (H, W) float32."""
    rgb = result.radiance[i].detach().cpu().numpy()
    ch = {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2],
          "A": result.coverage[i].detach().cpu().numpy()}
    for name, p in result.passes.items():
        a = p[i].detach().cpu().numpy()
        if a.shape[-1] == 1:
            ch[name] = a[..., 0]
        else:
            for c in range(a.shape[-1]):
                ch[f"{name}.{_AXES[c]}"] = a[..., c]
    return ch


def metadata(result: RenderResult, i: int) -> dict:
    """How scene ``i`` was rendered (Kubric-style ``metadata.json``)."""
    from torchrefract import IMAGE_REVISION, __version__  # noqa: PLC0415

    meta = {
        "torchrefract_version": __version__,
        "image_revision": IMAGE_REVISION,
        "scene": result.scenes[i].to_dict(),
        "batch_size": int(result.radiance.shape[0]),
        "timings_s_per_batch": result.timings,
        "torch_version": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "machine": platform.platform(),
    }
    if result.blends is not None:
        meta["auto_blend"] = blend_records(result, i)
    if result.predictions is not None and result.predictions[i] is not None:
        meta["auto_prediction"] = result.predictions[i]
    return meta


def blend_records(result: RenderResult, i: int) -> list[dict]:
    """``auto``: every variant in scene ``i``'s image, with its weight (JSON-ready)."""
    return [{"method": m, "options": o, "weight": w} for m, o, w in result.blends[i]]


def save_render(result: RenderResult, i: int, out_dir: str | Path,
                exr_compression: str = "zip") -> dict[str, Path]:
    """Write scene ``i`` of a result into ``out_dir`` (its EXR with ``exr_compression``:
    :data:`~torchrefract.output.images.EXR_COMPRESSIONS`); returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = result.scenes[i]
    paths = {"exr": out / f"{scene.name}.exr", "png": out / f"{scene.name}.png",
             "json": out / f"{scene.name}.json"}
    write_exr(paths["exr"], exr_channels(result, i), exr_compression)
    write_png(paths["png"], result.radiance[i].detach().cpu().numpy(), scene.exposure)
    meta = dict(metadata(result, i), exr_compression=exr_compression)
    write_text(paths["json"], json.dumps(meta, indent=2) + "\n")
    return paths
