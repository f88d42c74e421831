"""Where a render's tensors live: the G-buffer, lighting and materials moved as a whole to
the device the shading runs on (``RenderSettings.device``), and the shading run with that
device as torch's default for the tensors it creates.

The G-buffer is rasterized (``RenderSettings.rasterizer``) and built on the CPU (its C
kernel or tensor code); a CUDA render moves it, the lighting and the materials once, then
runs the methods' tensor code there (the fused C kernels are CPU-only). Inside
:func:`on_device`, factory calls without an explicit device (``torch.zeros(n)``,
``torch.tensor([...])``) create on the render's device, so the tensor code needs no device
argument threaded through every function; code that builds tensors from numpy states the
device (``torch.as_tensor(a, device=x.device)``).
"""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager, nullcontext
from typing import Any, Iterator

import torch


def to_device(obj: Any, device: torch.device) -> Any:
    """``obj`` with every tensor in it on ``device``: a tensor, a tuple or list of them, a
    dict's values, or a dataclass's fields (recursively; frozen ones are rebuilt with
    :func:`dataclasses.replace`). Other values are returned as they are."""
    if isinstance(obj, torch.Tensor):
        return obj if obj.device == device else obj.to(device)
    if isinstance(obj, tuple) and not hasattr(obj, "_fields"):
        return tuple(to_device(v, device) for v in obj)
    if isinstance(obj, list):
        return [to_device(v, device) for v in obj]
    if isinstance(obj, dict):
        return {k: to_device(v, device) for k, v in obj.items()}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        changes = {f.name: to_device(getattr(obj, f.name), device)
                   for f in dataclasses.fields(obj) if f.init}
        return dataclasses.replace(obj, **changes)
    return obj


@contextmanager
def on_device(device: torch.device) -> Iterator[None]:
    """Run the block with ``device`` as torch's default for new tensors (nothing on the
    CPU: the default is the CPU already, and the mode's per-op cost is skipped)."""
    with (nullcontext() if device.type == "cpu" else torch.device(device)):
        yield


__all__ = ["on_device", "to_device"]
