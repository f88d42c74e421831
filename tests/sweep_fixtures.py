"""Small sweep configs for the dataset tests (tiny images, shipped assets)."""

from __future__ import annotations

from pathlib import Path

import yaml
from conftest import ASSETS

SPOT = str(ASSETS / "meshes" / "spot.ply")
SUZANNE = str(ASSETS / "meshes" / "suzanne.ply")
STUDIO = str(ASSETS / "envmaps" / "studio_small_03.exr")
PARK = str(ASSETS / "envmaps" / "rooitou_park.exr")


def base_scene(res: int = 32) -> dict:
    """An inline base scene in SCENE_SPEC.md form at res x res pixels."""
    return {"mesh": SPOT, "envmap": {"path": STUDIO},
            "material": {"ior": 1.5, "roughness": 0.1},
            "camera": {"eye": [0, 0.4, 3.2], "target": [0, 0, 0], "width": res,
                       "height": res, "samples_per_pixel": 1},
            "method": "specular"}


def small_sweep(**sweep_changes) -> dict:
    """A grid of 2 IORs x 2 azimuths x 2 env maps = 8 samples at 32x32, with random draws."""
    sweep = {
        "material": {"ior": [1.33, 1.6], "roughness": {"uniform": [0.0, 0.4]}},
        "envmap": {"path": [STUDIO, PARK], "rotate_deg": {"uniform": [0, 360]}},
        "camera": {"orbit": {"azimuth_deg": [-25, 25], "elevation_deg": {"uniform": [0, 25]}},
                   "look_at_jitter": 0.05},
        "mesh": {"random_rotation": "yaw"},
    }
    sweep.update(sweep_changes)
    return {"name": "small", "base": base_scene(),
            "sampling": {"mode": "grid", "seed": 3}, "sweep": sweep}


def write_config(path: Path, data: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path
