"""Rendering in bounded memory: how many views one tensor pass takes, and the tiles a view
too large for one pass is shaded in (issue #27).

A pass over a frame of V sub-pixels (all views of the pass), N of them shaded at once, takes
about

    PASS_BYTES_FIXED + FRAME_BYTES * V + SHADE_BYTES * N

bytes above the process's own: ``FRAME_BYTES`` per sub-pixel of the frame (the G-buffer's
two layers and rays, the planes the marches test, the radiance, the passes, their box
filters) and ``SHADE_BYTES`` per shaded object sub-pixel (a method's intermediates).
Measured in docs/datasets.md, "Memory budget".

Why the tiles are sets of shaded sub-pixels, not pieces of the image: a pixel's refracted
rays are marched through the back layer (with internal bounces, the front layer too)
wherever they travel on the object's silhouette, ``rousiers`` reads that layer's mips over
a footprint, and supersampled pixels are box-filtered. A tile with a cropped G-buffer would
change the pixels near its edges. So a view's G-buffer is built once, whole, and each tile
is a :attr:`~torchrefract.geometry.gbuffer.GBuffer.shade` mask over it: every tile reads the
same layers, and each sub-pixel gets the untiled render's value, bit for bit
(tests/test_tiles.py). Tiles bound the shading (``SHADE_BYTES``); the frame's part is read
whole by every tile, so a view whose frame alone exceeds the budget is rendered in strips
of rows over its marched layers' triangle ids instead (:mod:`torchrefract.large`, the fused
kernels), or fails up front with an error naming its size and the budget.

Example:
    >>> from torchrefract import tiles
    >>> tiles.pass_bytes(256 * 256, 0) > tiles.PASS_BYTES_FIXED
    True
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import torch

from torchrefract.checks import ConfigError
from torchrefract.geometry.gbuffer import GBuffer
from torchrefract.kernels.index import put_, take
from torchrefract.kept import Recent
from torchrefract.scene import Camera
from torchrefract.settings import current

if TYPE_CHECKING:
    from torchrefract.methods.base import Shaded

FRAME_BYTES = 576
"""Bytes per sub-pixel of the frame that a pass holds whatever it shades: 520 measured at
most (one sample per pixel, ``rousiers`` with internal bounces on a roughness map, in
tiles; docs/datasets.md, "Memory budget")."""
SHADE_BYTES = 2048
"""Bytes per object sub-pixel shaded at once: 1,810 measured at most (the methods' tensor
code, ``rousiers`` with internal bounces and a sphere light); the fused kernels need next
to none."""
PASS_BYTES_FIXED = 64 << 20
"""What a pass takes whatever its size (tables, the pyramids' lookups), bytes."""
MIN_TILE = 1 << 12
"""The fewest object sub-pixels a tile shades: below, each tile's pass over the whole frame
(the background, the marched planes) would cost more than its shading."""


MEMINFO_MAX_AGE_S = 1.0
"""How long a reading of ``MemAvailable`` serves the renders after it (as cpu_load's
readings: renders in quick succession read /proc once a second, not every call)."""

def _available_bytes() -> int:
    """The memory the kernel reports available (Linux ``MemAvailable``; 4 GiB where
    unknown)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 4 << 30


_available = Recent(lambda: _available_bytes(), MEMINFO_MAX_AGE_S)


def memory_budget() -> int:
    """The bytes a render pass may take: ``RenderSettings.memory_budget_mb``, else 80% of
    the memory the kernel reports available (Linux ``MemAvailable``; 4 GiB where unknown),
    and on a GPU (``RenderSettings.device``) at most 80% of its free memory (the G-buffer is
    built on the host and shaded on the GPU)."""
    s = current()
    if s.memory_budget_mb is not None:
        return s.memory_budget_mb << 20
    budget = int(_available.get() * 0.8)
    dev = s.torch_device()
    if dev.type == "cuda":
        import torch  # noqa: PLC0415

        budget = min(budget, int(torch.cuda.mem_get_info(dev)[0] * 0.8))
    return budget


def pass_bytes(subpixels: int, shaded: int) -> int:
    """Estimated peak bytes of a pass over ``subpixels`` (its whole frame) shading
    ``shaded`` object sub-pixels at once (module docstring)."""
    return PASS_BYTES_FIXED + FRAME_BYTES * subpixels + SHADE_BYTES * shaded


def size_text(n: int, up: bool = False) -> str:
    """Bytes as ``1.5 GiB``, ``300 MB`` or ``65.1 MB``, rounded down (``up``: up, so that a
    need over a budget never reads as equal to it)."""
    unit, digits = (2**30, 1) if n >= 2**30 else (2**20, 0 if n >= 100 << 20 else 1)
    v = math.floor(n / unit * 10**digits) if not up else math.ceil(n / unit * 10**digits)
    return f"{v / 10**digits:.{digits}f} {'GiB' if unit == 2**30 else 'MB'}"


def fits_whole(camera: Camera, budget: int) -> bool:
    """Whether one view of ``camera`` fits ``budget`` bytes as one G-buffer, its shading in
    tiles where needed (else it renders in strips, :mod:`torchrefract.large`)."""
    per_view = camera.width * camera.height * camera.samples_per_pixel ** 2
    return pass_bytes(per_view, min(per_view, MIN_TILE)) <= budget


def check_view(camera: Camera, budget: int) -> None:
    """Raise ConfigError, before any work, where one view of ``camera`` does not fit
    ``budget`` bytes even in the smallest tiles (its frame's part alone is too large)."""
    per_view = camera.width * camera.height * camera.samples_per_pixel ** 2
    need = pass_bytes(per_view, min(per_view, MIN_TILE))
    if need > budget:
        raise ConfigError(
            f"render: one {camera.width}x{camera.height} view at samples_per_pixel "
            f"{camera.samples_per_pixel} ({per_view:,} sub-pixels) needs about "
            f"{size_text(need, up=True)} even in tiles (its G-buffer, rays and marched layers, "
            f"{FRAME_BYTES} bytes per sub-pixel, which every tile reads whole), over the "
            f"memory budget of {size_text(budget)} (RenderSettings.memory_budget_mb, "
            f"TORCHREFRACT_MEMORY_MB; default: 80% of the available memory): render it "
            f"smaller or with fewer samples per pixel")


def views_per_pass(camera: Camera, budget: int) -> int:
    """How many views of ``camera`` one pass shades whole within ``budget`` (at least 1:
    a view that alone does not fit is shaded in tiles, :func:`shade`)."""
    per_view = camera.width * camera.height * camera.samples_per_pixel ** 2
    return max(1, (budget - PASS_BYTES_FIXED) // (pass_bytes(per_view, per_view)
                                                  - PASS_BYTES_FIXED))


def tile_size(frame_subpixels: int, budget: int) -> int:
    """Object sub-pixels one tile shades in a pass over ``frame_subpixels`` within
    ``budget`` (at least :data:`MIN_TILE`)."""
    room = budget - pass_bytes(frame_subpixels, 0)
    return max(MIN_TILE, room // SHADE_BYTES)


def split(idx: torch.Tensor, size: int) -> list[torch.Tensor]:
    """``idx`` (N,) cut into near-equal consecutive pieces of at most ``size``."""
    n = -(-idx.numel() // size)
    return list(torch.tensor_split(idx, n)) if n > 1 else [idx]


def checked(entry, out, shape: tuple[int, int, int]):
    """A method's ``shade`` result as the render needs it: a ``Shaded`` whose radiance is
    (B, H, W, 3) and whose passes are (B, H, W, C) tensors over the G-buffer's ``shape``
    (a plug-in method's mistake named here, not deep in the box filter)."""
    from torchrefract.methods.base import Shaded  # noqa: PLC0415 (a scene loads no method)

    name = f"method {getattr(entry, 'name', entry)!r}: shade()"
    if not isinstance(out, Shaded):
        raise ConfigError(f"{name} returned {type(out).__name__}, expected a Shaded")
    want = (*shape, 3)
    if not torch.is_tensor(out.radiance) or tuple(out.radiance.shape) != want:
        got = tuple(out.radiance.shape) if torch.is_tensor(out.radiance) else out.radiance
        raise ConfigError(f"{name} returned radiance of shape {got}, expected {want}")
    for k, v in out.passes.items():
        if not torch.is_tensor(v) or v.dim() != 4 or tuple(v.shape[:3]) != tuple(shape):
            got = tuple(v.shape) if torch.is_tensor(v) else type(v).__name__
            raise ConfigError(f"{name} returned pass {k!r} of shape {got}, expected "
                              f"{(*shape, 'C')}")
    return out


def shade(entry, g: GBuffer, lighting, materials, options, state, budget: int) -> Shaded:
    """``entry.shade`` over ``g``, in tiles of at most :func:`tile_size` object sub-pixels
    where all of them do not fit ``budget`` at once: each tile a ``shade`` mask over the
    whole G-buffer, its sub-pixels' radiance and passes copied into the first tile's
    (whose other pixels, the background, every tile computes alike).

    The methods turn the rough interfaces' energies on for a whole pass where any shaded
    sub-pixel is rough (``shading.paths``, ``shading.fused``); where a roughness map makes
    some sub-pixels smooth and others rough, every tile also shades the first rough one, so
    that the switch is the untiled pass's (its value is the same in each).
    """
    from torchrefract.methods.base import Shaded  # noqa: PLC0415 (a scene loads no method)

    b, h, w = g.shape
    idx = g.object_index()
    size = tile_size(b * h * w, budget)
    if not entry.shades_object_index or idx.numel() <= size:
        return checked(entry, entry.shade(g, lighting, materials, options, state), g.shape)
    pieces = split(idx, size)
    alpha = materials.roughness_at(g.object_views(), take(g.front.uv.reshape(-1, 2), idx))
    rough = alpha > 0
    mixed = bool(rough.any()) and not bool(rough.all())
    witness = take(idx, rough.nonzero()[0]) if mixed else None  # (1,)
    radiance, passes = None, {}
    for piece in pieces:
        mask = torch.zeros(b * h * w, dtype=torch.bool).index_fill_(0, piece, True)
        if witness is not None:
            mask.index_fill_(0, witness, True)
        # a tile is not the whole first pass: the levels after it wait for the caller
        out = checked(entry, entry.shade(dataclasses.replace(
            g, shade=mask.view(b, h, w), lattice=None), lighting, materials, options, state),
            g.shape)
        if radiance is None:  # the first tile: the frame every other one is copied into
            # (copies: a method may hand out views of buffers it reads, the G-buffer's)
            radiance = out.radiance.clone(memory_format=torch.contiguous_format)
            passes = {k: v.clone(memory_format=torch.contiguous_format)
                      for k, v in out.passes.items()}
            del out
            continue
        put_(radiance.view(-1, 3), piece, take(out.radiance.reshape(-1, 3), piece))
        for k, v in out.passes.items():
            c = v.shape[-1]
            if k not in passes:  # a pass the first tile lacked: zero where not shaded
                passes[k] = torch.zeros(v.shape, dtype=v.dtype)
            put_(passes[k].view(-1, c), piece, take(v.reshape(-1, c), piece))
        del out
    return Shaded(radiance, passes)


__all__ = ["FRAME_BYTES", "MIN_TILE", "PASS_BYTES_FIXED", "SHADE_BYTES", "check_view",
           "fits_whole",
           "memory_budget", "pass_bytes", "shade", "split", "tile_size", "views_per_pass"]
