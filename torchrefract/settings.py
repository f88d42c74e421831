"""How a render runs (not what it renders): threads, kernels, compilation, adaptive
sampling (on by default), the memory budget, the cache folder and
the allocator, passed to :func:`torchrefract.render`, the CLI, sweeps and
``RenderStream`` as one :class:`RenderSettings`.

The settings hold for the duration of one call, through a context variable that the
kernels' dispatch reads (:func:`current`); nothing is switched for the whole process. The
environment variables below are only the documented defaults of :meth:`RenderSettings.from_env`
(read when settings are made, never at import):

====================================  =============================================
``TORCHREFRACT_NATIVE=0``              ``native=False``: tensor code, not the C kernels
``TORCHREFRACT_NATIVE_SIMD=0``         ``native_simd=False``: the march's scalar search
``TORCHREFRACT_FUSED=0``               ``fused=False``: the tensor code, not the fused kernels
``TORCHREFRACT_ADAPTIVE=0``            ``adaptive=False``: every (sub-)pixel shaded
``TORCHREFRACT_COMPILE=1``             ``compile=True``: torch.compile the march
``TORCHREFRACT_HEAP_REUSE=1`` (``0``)  ``heap_reuse=True`` (``0``: never, even if asked)
``TORCHREFRACT_THREADS=N``             ``threads=N``
``TORCHREFRACT_ADAPT_THREADS=0``       ``adapt_threads=False``: torch's count even under load
``TORCHREFRACT_MEMORY_MB=N``           ``memory_budget_mb=N``
``TORCHREFRACT_CACHE=DIR``             ``cache_dir=DIR``
``TORCHREFRACT_DEVICE=cuda``           ``device="cuda"``: shade on the GPU (tensor code)
``TORCHREFRACT_RASTERIZER=opengl``     ``rasterizer="opengl"``: the OpenGL visibility passes
====================================  =============================================

Only ``threads`` and ``heap_reuse`` touch process-wide state: ``threads`` (or, where it is
None, the cores left free by other processes: ``adapt_threads``) is torch's intra-op thread
count for the call (restored after it); ``heap_reuse`` tunes
glibc's allocator for the whole process (:mod:`torchrefract.heap`), which the caller asks
for explicitly.

Example:
    >>> import torchrefract as tr
    >>> fast = tr.RenderSettings(threads=2)
    >>> out = tr.render(scenes, settings=fast)            # doctest: +SKIP
"""

from __future__ import annotations

import contextvars
import dataclasses
import os
import re
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from torchrefract.checks import ConfigError

_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")
RASTERIZERS = ("auto", "native", "opengl")
"""The values of :attr:`RenderSettings.rasterizer`."""


def _env_count(name: str) -> int | None:
    """A positive integer from the environment, else None (unset or empty); anything else
    is a ConfigError naming the variable (a typo used to fall back in silence)."""
    v = os.environ.get(name, "").strip()
    if not v:
        return None
    if not v.isdigit() or int(v) < 1:
        raise ConfigError(f"{name}={v!r}: expected a whole number >= 1 (or unset)")
    return int(v)


def _env_flag(name: str, default: bool) -> bool:
    v = os.environ.get(name, "").strip().lower()
    if v in _TRUE:
        return True
    if v in _FALSE:
        return False
    if v:
        raise ConfigError(f"{name}={v!r}: expected one of {sorted(_TRUE + _FALSE)} (or unset)")
    return default


MAX_THREADS = 4096
"""Most threads a render may ask for (torch takes a C int)."""


@dataclass(frozen=True)
class RenderSettings:
    """How a render runs; every field's default is the fastest correct choice."""

    threads: int | None = None
    """torch CPU threads for the call (None: torch's own count, lowered for the call by the
    cores other processes keep busy where ``adapt_threads``)."""
    adapt_threads: bool = True
    """With ``threads`` None: where other processes keep cores busy at the start of a call,
    use only the free ones for it (at least 1; :mod:`torchrefract.cpu_load`): one thread
    per core is slower than fewer when a core is taken."""
    native: bool = True
    """The C kernels (march, G-buffer, cone) where they build; the tensor code otherwise
    (the same images)."""
    native_simd: bool = True
    """The march's AVX2 search where the CPU has it (the same values as the scalar one)."""
    fused: bool = True
    """A method's per-pixel shading as one native kernel where it covers the scene
    (:mod:`torchrefract.shading.fused`; the tensor code otherwise, and wherever a gradient
    is wanted): the same images within float32 rounding."""
    adaptive: bool = True
    """Shade no more pixels than the image needs (:mod:`torchrefract.geometry.adaptive`):
    with ``samples_per_pixel`` n > 1, all n x n sub-pixels only where the G-buffer changes
    inside the pixel, one center sample elsewhere; with one sample, the 2x2 lattice's
    pixels, and the pixels between them only where their G-buffer or the lattice's
    radiance is not smooth (the others interpolated). An approximation of the full
    sampling at a fraction of its shading, as close to converged truth out of sample
    (docs/decisions.md, "Adaptive shading on by default"); False shades every
    (sub-)pixel. Off by itself where matte or flow passes are asked for."""
    compile: bool = False
    """torch.compile the march's tensor code (seconds of start-up per process)."""
    heap_reuse: bool = False
    """Tune glibc's allocator for the whole process (:mod:`torchrefract.heap`): asked for by
    the ``torchrefract`` command; never by default in a host process."""
    memory_budget_mb: int | None = None
    """The memory a render pass may take (MB): a batch is shaded in chunks of views that fit
    it, a view that alone does not in tiles (:mod:`torchrefract.tiles`: the same pixels),
    and a view whose frame does not fit even so fails up front, naming its size and the
    budget (None: 80% of the machine's available memory at the render)."""
    cache_dir: str | None = None
    """Folder of the built kernels and tables (None: ``$XDG_CACHE_HOME/torchrefract`` or
    ``~/.cache/torchrefract``)."""
    device: str = "cpu"
    """Where the shading runs: ``cpu``, ``cuda`` / ``cuda:N`` (the tensor code on that GPU;
    the G-buffer is still rasterized and built on the CPU, then moved), or
    ``auto`` (``cuda`` where torch sees a GPU, else ``cpu``). The result's tensors are on
    that device."""
    rasterizer: str = "auto"
    """What draws the G-buffer's triangle ids (:mod:`torchrefract.geometry.raster`):
    ``native`` (the C rasterizer, csrc/raster.c: both layers in one pass; an error where
    the native kernels do not build), ``opengl`` (pyrender's EGL context: two passes per
    view), or ``auto`` (``native`` where the native kernels run, else ``opengl``). The
    exact G-buffer built from either is the same but for pixel centers within ~1/256
    pixel of an edge."""

    def __post_init__(self):
        for name, most in (("threads", MAX_THREADS), ("memory_budget_mb", 1 << 40)):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1
                                  or v > most):
                raise ConfigError(f"RenderSettings.{name}: expected an integer >= 1 and <= "
                                  f"{most}, or None, got {v!r}")
        for f in dataclasses.fields(self):
            if f.type in ("bool", bool) and not isinstance(getattr(self, f.name), bool):
                raise ConfigError(f"RenderSettings.{f.name}: expected True or False, got "
                                  f"{getattr(self, f.name)!r}")
        if self.cache_dir is not None and not isinstance(self.cache_dir, (str, os.PathLike)):
            raise ConfigError(f"RenderSettings.cache_dir: expected a folder path or None, "
                              f"got {self.cache_dir!r}")
        if not isinstance(self.device, str) or not re.fullmatch(r"cpu|auto|cuda(:\d+)?",
                                                                 self.device):
            raise ConfigError(f"RenderSettings.device: expected 'cpu', 'cuda', 'cuda:N' or "
                              f"'auto', got {self.device!r}")
        if self.rasterizer not in RASTERIZERS:
            raise ConfigError(f"RenderSettings.rasterizer: expected one of "
                              f"{', '.join(map(repr, RASTERIZERS))}, got {self.rasterizer!r}")
        if self.rasterizer == "native" and not self.native:
            raise ConfigError("RenderSettings.rasterizer: 'native' needs the native kernels, "
                              "which native=False turns off")

    def torch_device(self):
        """The torch.device the shading runs on (``auto`` resolved).

        Raises:
            ConfigError: a CUDA device is asked for and torch sees none (or not that one).
        """
        import torch  # noqa: PLC0415

        if self.device == "cpu":
            return torch.device("cpu")
        if self.device == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        dev = torch.device(self.device)
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (dev.index or 0) >= count:
            raise ConfigError(f"RenderSettings.device: {self.device!r} asked for, but torch "
                              f"{torch.__version__} sees {count} CUDA device(s)")
        return dev

    @classmethod
    def from_env(cls, **overrides) -> "RenderSettings":
        """The defaults as the environment variables (module docstring) set them."""
        base = cls(
            threads=_env_count("TORCHREFRACT_THREADS"),
            adapt_threads=_env_flag("TORCHREFRACT_ADAPT_THREADS", True),
            native=_env_flag("TORCHREFRACT_NATIVE", True),
            native_simd=_env_flag("TORCHREFRACT_NATIVE_SIMD", True),
            fused=_env_flag("TORCHREFRACT_FUSED", True),
            adaptive=_env_flag("TORCHREFRACT_ADAPTIVE", True),
            memory_budget_mb=_env_count("TORCHREFRACT_MEMORY_MB"),
            compile=_env_flag("TORCHREFRACT_COMPILE", False),
            heap_reuse=_env_flag("TORCHREFRACT_HEAP_REUSE", False),
            cache_dir=os.environ.get("TORCHREFRACT_CACHE") or None,
            device=os.environ.get("TORCHREFRACT_DEVICE") or "cpu",
            rasterizer=os.environ.get("TORCHREFRACT_RASTERIZER") or "auto",
        )
        return dataclasses.replace(base, **overrides)

    def replace(self, **changes) -> "RenderSettings":
        return dataclasses.replace(self, **changes)


def deprecated_switch(old: str, field: str, env: str, enabled: bool) -> None:
    """The old process-wide switches (``set_native``, ``set_compile``): a DeprecationWarning,
    and the environment's default for ``field`` set for this process."""
    import warnings  # noqa: PLC0415

    warnings.warn(f"torchrefract.{old} is deprecated: pass settings=torchrefract."
                  f"RenderSettings({field}=...) to render()", DeprecationWarning, stacklevel=3)
    os.environ[env] = "1" if enabled else "0"


def cache_folder(s: RenderSettings | None = None) -> Path:
    """The cache folder of ``s`` (default: the current settings): ``cache_dir``, else
    ``$TORCHREFRACT_CACHE``, ``$XDG_CACHE_HOME/torchrefract`` or ``~/.cache/torchrefract``.

    The environment is read here too, not only by :meth:`RenderSettings.from_env`: settings
    made in code for another field (``RenderSettings(threads=1)``) must not move the caches
    of a process whose user moved them (two renders would then read different tables)."""
    s = s if s is not None else current()
    if s.cache_dir:
        return Path(s.cache_dir)
    env = os.environ.get("TORCHREFRACT_CACHE")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "torchrefract"


_CURRENT: contextvars.ContextVar[RenderSettings | None] = contextvars.ContextVar(
    "torchrefract_settings", default=None)


def current() -> RenderSettings:
    """The settings of the render in progress (outside one: the environment's defaults)."""
    s = _CURRENT.get()
    return s if s is not None else RenderSettings.from_env()


@contextmanager
def using(settings: RenderSettings | None) -> Iterator[RenderSettings]:
    """Run the block under ``settings`` (None: those in force, or the environment's).

    Sets torch's thread count for the block where ``settings.threads`` is given, or where
    other processes keep cores busy (``adapt_threads``), and restores it; turns heap reuse
    on where ``settings.heap_reuse`` asks for it. Nested blocks keep the outer count."""
    s = settings if settings is not None else current()
    if not isinstance(s, RenderSettings):
        raise ConfigError(f"settings: expected a torchrefract.RenderSettings, got "
                          f"{type(s).__name__}")
    outer = _CURRENT.get() is None
    token = _CURRENT.set(s)
    threads_before = None
    try:
        want = s.threads
        adapt = want is None and s.adapt_threads and outer
        if want is not None or adapt:
            import torch  # noqa: PLC0415

            from torchrefract.cpu_load import threads_for  # noqa: PLC0415

            threads_before = torch.get_num_threads()
            want = threads_for(threads_before) if adapt else want
            if threads_before != want:
                torch.set_num_threads(want)
            else:
                threads_before = None
        if s.heap_reuse:
            from torchrefract import heap  # noqa: PLC0415

            heap.set_heap_reuse(True)
        yield s
    finally:
        if threads_before is not None:
            import torch  # noqa: PLC0415

            torch.set_num_threads(threads_before)
        _CURRENT.reset(token)


__all__ = ["RenderSettings", "cache_folder", "current", "using"]
