"""Shared test fixtures: repository paths, small synthetic assets."""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import trimesh  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
ASSETS = ROOT / "assets"
SH_SMALL = {"view_rings": 10, "surface_samples": 2048}
"""An ``sh`` table of ~1 s (200 directions per sample): the tests' ``sh`` scenes."""


def small_scene_yaml(tmp_path: Path, name: str = "small", **changes) -> Path:
    """The demo scene at 40x32, 1 spp, with ``changes`` to its top-level keys, as a file."""
    import yaml  # noqa: PLC0415

    data = yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())
    data["mesh"] = str(ASSETS / "meshes" / "spot.ply")
    data["envmap"]["path"] = str(ASSETS / "envmaps" / "studio_small_03.exr")
    data["camera"].update(width=40, height=32, samples_per_pixel=1)
    data.update(changes)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def one_thread():
    """Run a module's many small tensor ops on one thread.

    Measured on the shared 2-core machine: with 2 intra-op threads and the other core busy,
    every op on >= 32k elements waited ~10 ms for the second thread (eval of 39k directions:
    2.8 s with 2 threads, 0.025 s with 1).
    """
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def mi_vectorized():
    """Mitsuba 3 in a vectorized (LLVM) variant, for tests that draw millions of BSDF
    samples; skipped where Mitsuba is missing or only ``scalar_rgb`` works."""
    pytest.importorskip("mitsuba")
    from torchrefract.truth.mitsuba import mitsuba  # noqa: PLC0415

    try:
        mi = mitsuba()
    except ImportError as exc:
        pytest.skip(f"Mitsuba unusable here: {exc}")
    if mi.variant().startswith("scalar"):
        pytest.skip("needs a vectorized Mitsuba variant (llvm_ad_rgb): millions of samples")
    return mi


@pytest.fixture(scope="session")
def sphere_ply(tmp_path_factory) -> Path:
    """A unit icosphere (subdivision 6, 81,920 faces, radius 1) as PLY, no stored normals."""
    path = tmp_path_factory.mktemp("meshes") / "sphere6.ply"
    trimesh.creation.icosphere(subdivisions=6, radius=1.0).export(path)
    return path


def smooth_env_texels(h: int = 64, w: int = 128) -> np.ndarray:
    """A smooth positive environment: an affine function of the direction per channel."""
    v = (np.arange(h) / (h - 1)) * np.pi
    u = (np.arange(w) + 0.5) / w * 2 * np.pi
    vv, uu = np.meshgrid(v, u, indexing="ij")
    # Spec: u = atan2(x, -z) / 2pi, v = acos(y) / pi.
    x, y, z = np.sin(vv) * np.sin(uu), np.cos(vv), -np.sin(vv) * np.cos(uu)
    img = np.stack([1.0 + 0.6 * x + 0.2 * y, 1.0 + 0.5 * y - 0.3 * z, 1.0 + 0.7 * z + 0.1 * x],
                   -1)
    return img.astype(np.float32)


@pytest.fixture(scope="session")
def smooth_env_exr(tmp_path_factory) -> Path:
    from torchrefract.output.images import write_exr

    img = smooth_env_texels()
    path = tmp_path_factory.mktemp("env") / "smooth.exr"
    write_exr(path, {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]})
    return path
