"""The files of one rendered sample, as bytes: the EXR (R, G, B, A and every pass, as
``torchrefract render`` writes it), the sRGB PNG preview, their sha256, and the EXR's
channel layout (recorded in the manifest)."""

from __future__ import annotations

import hashlib
import io

import numpy as np

from torchrefract.scene.model import Scene


def encode_exr(channels: dict[str, np.ndarray], compression: str = "zip") -> bytes:
    """The bytes :func:`torchrefract.output.images.write_exr` writes for these channels."""
    from torchrefract.output.images import exr_file  # noqa: PLC0415

    buf = io.BytesIO()
    with exr_file(channels, compression) as f:
        f.write(buf)
    return buf.getvalue()


def encode_png(rgb: np.ndarray, exposure: float = 0.0) -> bytes:
    """The bytes :func:`torchrefract.output.images.write_png` writes: the sRGB PNG preview
    of linear radiance (H, W, 3)."""
    from torchrefract.output.images import png_bytes  # noqa: PLC0415

    return png_bytes(rgb, exposure)


def channel_layout(result, i: int = 0) -> dict:
    """Which EXR channels hold what: radiance, coverage and each pass."""
    passes = {}
    for name, p in result.passes.items():
        c = int(p.shape[-1])
        passes[name] = [name] if c == 1 else [f"{name}.{'XYZW'[k]}" for k in range(c)]
    return {"radiance": ["R", "G", "B"], "coverage": ["A"], "passes": passes}


def _encode(res, j: int, scene: Scene, exr_compression: str = "zip") -> dict:
    """The EXR and PNG bytes of scene ``j`` of a result, and their sha256."""
    from torchrefract.output.export import exr_channels  # noqa: PLC0415

    exr = encode_exr(exr_channels(res, j), exr_compression)
    png = encode_png(res.radiance[j].detach().cpu().numpy(), scene.exposure)
    return {"exr": exr, "png": png,
            "sha256": {"exr": hashlib.sha256(exr).hexdigest(),
                       "png": hashlib.sha256(png).hexdigest()}}

