"""What a sample's record says about it, deterministically (no times or hosts): the
resolved parameters, the full scene, the camera's intrinsics and extrinsics, seeds and
versions (the manifest's and the loaders' metadata). Written into a dataset, its input paths
are relative to the dataset folder (:mod:`~torchrefract.dataset.paths`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from torchrefract.dataset.paths import portable_record
from torchrefract.dataset.sweep import Sample, SweepConfig
from torchrefract.scene.model import Camera


def camera_metadata(cam: Camera) -> dict:
    """Intrinsics and extrinsics of a scene camera, OpenCV convention.

    - ``world_to_camera``: 4x4, camera x right, y down, z forward (the viewing direction);
      ``X_cam = R X_world + t``.
    - ``intrinsics``: ``fx, fy, cx, cy`` in pixels for ``u = fx X/Z + cx``,
      ``v = fy Y/Z + cy`` where pixel (column i, row j) is centered at (u, v) = (i, j)
      (OpenCV); SCENE_SPEC.md's continuous coordinates (centers at i + 0.5) are u + 0.5.
    """
    from torchrefract.geometry.camera import camera_frame  # noqa: PLC0415

    eye, r, u, f = camera_frame(cam)
    rot = np.stack([r, -u, f])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ eye
    fy = cam.height / (2.0 * math.tan(math.radians(cam.yfov_deg) / 2.0))
    # Square pixels: the spec's horizontal half-angle is t * (W / H), so fx = fy.
    return {
        "convention": "opencv (x right, y down, z forward; pixel (i, j) centered at (i, j))",
        "width": cam.width, "height": cam.height,
        "intrinsics": {"fx": fy, "fy": fy, "cx": cam.width / 2.0 - 0.5,
                       "cy": cam.height / 2.0 - 0.5},
        "K": [[fy, 0.0, cam.width / 2.0 - 0.5], [0.0, fy, cam.height / 2.0 - 0.5],
              [0.0, 0.0, 1.0]],
        "world_to_camera": w2c.tolist(),
    }


def _sample_meta(cfg: SweepConfig, sample: Sample, root: str | Path | None = None) -> dict:
    """Everything that decides a sample (deterministic: no times or hosts in it); with a
    dataset folder ``root``, input paths relative to it (else absolute)."""
    from torchrefract import IMAGE_REVISION, __version__  # noqa: PLC0415

    scene = sample.scene
    meta = {
        "sample_id": sample.sample_id,
        "index": sample.params["index"],
        "sweep": cfg.name,
        "config_hash": cfg.config_hash,
        "seed": cfg.sampling.seed,
        "sample_seed": [cfg.sampling.seed, sample.params["index"]],
        "method": scene.method,
        "params": sample.params,
        "scene": scene.to_dict(),
        "camera": camera_metadata(scene.camera),
        "torchrefract_version": __version__,
        "image_revision": IMAGE_REVISION,
    }
    return meta if root is None else portable_record(meta, root)

