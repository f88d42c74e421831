"""Image files: OpenEXR read/write, Radiance .hdr (RGBE) read/write, sRGB PNG previews.

EXR files hold linear float32 radiance, never tonemapped. Writes are atomic
(:mod:`torchrefract.output.atomic`) so an interrupted run never leaves a corrupt file.
"""

from __future__ import annotations

import io

from pathlib import Path

import numpy as np

from torchrefract.checks import ConfigError
from torchrefract.output.atomic import atomic_path, write_bytes


EXR_COMPRESSIONS = {"zip": "ZIP", "zips": "ZIPS", "rle": "RLE", "piz": "PIZ", "zstd": "ZSTD",
                    "none": "NO"}
"""The lossless OpenEXR compressions a file can be written with (``exr_compression``, the
same pixels whichever): ``zip``, the default, read by every EXR reader; ``rle`` faster to
write, larger; ``zstd`` smaller and faster to read, but read only by OpenEXR 3.4 and
later; ``none`` the fastest and largest (docs/datasets.md, section 4)."""


def check_exr_compression(value, key: str = "exr_compression") -> str:
    """``value`` if it names one of :data:`EXR_COMPRESSIONS`, else a ConfigError naming
    ``key``."""
    if not isinstance(value, str) or value not in EXR_COMPRESSIONS:
        raise ConfigError(f"{key}: {value!r} is not one of {', '.join(EXR_COMPRESSIONS)}")
    return value


def exr_file(channels: dict[str, np.ndarray], compression: str = "zip"):
    """The ``OpenEXR.File`` torchrefract writes for float32 channels (each (H, W)): one
    scanline part, ``compression`` (:data:`EXR_COMPRESSIONS`)."""
    import OpenEXR  # noqa: PLC0415

    code = getattr(OpenEXR, EXR_COMPRESSIONS[check_exr_compression(compression)]
                   + "_COMPRESSION")
    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    return OpenEXR.File({"compression": code, "type": OpenEXR.scanlineimage}, data)


def write_exr(path: str | Path, channels: dict[str, np.ndarray],
              compression: str = "zip") -> None:
    """Write float32 channels (each (H, W)) to an OpenEXR file, atomically
    (:func:`exr_file`).

    Example:
        >>> write_exr("x.exr", {"R": r, "G": g, "B": b, "A": a})  # doctest: +SKIP
    """
    path = Path(path)
    with atomic_path(path, suffix=path.suffix) as tmp:
        with exr_file(channels, compression) as f:
            f.write(str(tmp))


def read_exr(path: str | Path) -> dict[str, np.ndarray]:
    """Read every channel of an OpenEXR file as float32 (H, W) arrays."""
    import OpenEXR  # noqa: PLC0415

    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            return {k: np.asarray(v.pixels, dtype=np.float32) for k, v in f.channels().items()}
    except Exception as exc:
        raise ConfigError(f"{path}: cannot read as OpenEXR ({exc})") from None


def read_hdr(path: str | Path) -> np.ndarray:
    """Read a Radiance RGBE (.hdr/.pic) image, flat or run-length encoded, as (H, W, 3) float32."""
    raw = Path(path).read_bytes()
    pos = 0

    def line() -> bytes:
        nonlocal pos
        end = raw.index(b"\n", pos)
        s = raw[pos:end]
        pos = end + 1
        return s

    try:
        first = line()
        if not first.startswith(b"#?"):
            raise ValueError("missing #? signature")
        while True:
            s = line()
            if s == b"":
                break
            if s.startswith(b"FORMAT=") and s.strip() != b"FORMAT=32-bit_rle_rgbe":
                raise ValueError(f"unsupported {s.decode(errors='replace')}")
        res = line().split()
        if len(res) != 4 or res[0] != b"-Y" or res[2] != b"+X":
            raise ValueError(f"unsupported orientation {b' '.join(res).decode()}")
        h, w = int(res[1]), int(res[3])
        out = np.empty((h, w, 4), np.uint8)
        buf = np.frombuffer(raw, np.uint8)
        for y in range(h):
            if 8 <= w < 32768 and buf[pos] == 2 and buf[pos + 1] == 2 and buf[pos + 2] < 128:
                if (int(buf[pos + 2]) << 8 | int(buf[pos + 3])) != w:
                    raise ValueError(f"scanline {y}: bad length")
                pos += 4
                for c in range(4):
                    x = 0
                    while x < w:
                        code = int(buf[pos])
                        pos += 1
                        run = code > 128  # a run of one value, else a literal dump
                        n = code - 128 if run else code
                        if n == 0 or x + n > w:
                            raise ValueError(f"scanline {y}: bad run length {n} at x={x}")
                        if run:
                            out[y, x:x + n, c] = buf[pos]
                            pos += 1
                        else:
                            if pos + n > len(buf):
                                raise ValueError(f"scanline {y}: data ends early")
                            out[y, x:x + n, c] = buf[pos:pos + n]
                            pos += n
                        x += n
            else:  # flat scanline
                out[y] = buf[pos:pos + 4 * w].reshape(w, 4)
                pos += 4 * w
    except (ValueError, IndexError) as exc:
        raise ConfigError(f"{path}: not a readable Radiance .hdr file ({exc})") from None
    e = out[..., 3].astype(np.int32)
    f = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)  # 2^(e-128) / 256
    return (out[..., :3].astype(np.float64) * f[..., None]).astype(np.float32)


def write_hdr(path: str | Path, rgb: np.ndarray) -> None:
    """Write (H, W, 3) linear radiance as a flat (uncompressed) Radiance RGBE file."""
    rgb = np.asarray(rgb, np.float64)
    h, w, _ = rgb.shape
    m = rgb.max(-1)
    mant, exp = np.frexp(m)
    scale = np.where(m > 1e-32, mant * 256.0 / np.maximum(m, 1e-300), 0.0)
    rgbe = np.zeros((h, w, 4), np.uint8)
    rgbe[..., :3] = np.clip(rgb * scale[..., None], 0, 255).astype(np.uint8)
    rgbe[..., 3] = np.where(m > 1e-32, exp + 128, 0).astype(np.uint8)
    head = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n".encode()
    path = Path(path)
    write_bytes(path, head + rgbe.tobytes())


def linear_to_srgb8(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear radiance (H, W, 3) -> 8-bit sRGB with ``2**exposure`` gain and clipping."""
    x = np.clip(np.nan_to_num(rgb * (2.0 ** exposure)), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


PNG_LEVEL = 1
"""zlib level of the PNG previews: the fastest. A preview is only a view of the EXR, and at
PIL's default level its encoding weighed on a dataset's pace for files little smaller
(docs/datasets.md, section 4)."""


def png_bytes(rgb: np.ndarray, exposure: float = 0.0) -> bytes:
    """The sRGB PNG preview of linear radiance (H, W, 3), as bytes (PNG_LEVEL)."""
    from PIL import Image  # noqa: PLC0415

    buf = io.BytesIO()
    Image.fromarray(linear_to_srgb8(rgb, exposure)).save(buf, format="PNG",
                                                         compress_level=PNG_LEVEL)
    return buf.getvalue()


def write_png(path: str | Path, rgb: np.ndarray, exposure: float = 0.0) -> None:
    """Write an sRGB PNG preview of linear radiance (H, W, 3), atomically."""
    write_bytes(path, png_bytes(rgb, exposure))
