"""``torchrefract.IMAGE_REVISION`` means what datasets take it for: the default images of a
few small scenes are kept with the revision they were rendered at (tests/data/
image_revision.npz), and a change of those images without a new revision fails here.

Where the change is meant (a method's result, adaptive sampling, a default option): raise
``IMAGE_REVISION`` by one in torchrefract/__init__.py, then record the images again:

    .venv/bin/python tests/test_image_revision.py --record

The comparison allows what another CPU's rounding gives (the kernels take the machine's
own instructions), not a change of the images: on the object pixels the mean absolute
difference within 1e-3 of the mean value, 99% of them within 2% relative; the background
pixels alike.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import SH_SMALL

import torchrefract as tr

ROOT = Path(__file__).resolve().parent.parent
DATA = Path(__file__).resolve().parent / "data" / "image_revision.npz"

# (name, suite scene, method, method_options, size, samples per pixel): the default
# settings (adaptive sampling on) across methods, bounces, a light and a roughness map
CASES = [
    ("demo_rousiers_2x2", "../demo.yaml", "rousiers", {}, 40, 2),
    ("sphere_specular", "sphere_a03.yaml", "specular", {}, 48, 1),
    ("sphere_prefiltered", "sphere_a03.yaml", "prefiltered", {}, 48, 1),
    ("slab_light_ib2", "slab_light.yaml", "rousiers", {"internal_bounces": 2}, 48, 1),
    ("globe_jump_lean", "globe_jump.yaml", "lean", {}, 48, 1),
    ("torus_ib_auto", "torus_a01.yaml", "rousiers", {"internal_bounces": "auto"}, 48, 1),
    ("globe_jump_rousiers_2x2", "globe_jump.yaml", "rousiers", {}, 32, 2),
    ("bunny_lean_2x2", "bunny_a01.yaml", "lean", {}, 32, 2),
    ("teapot_sh_2x2", "teapot_a01.yaml", "sh", SH_SMALL, 32, 2),
]


def render_cases() -> dict[str, np.ndarray]:
    """Each case's radiance (H, W, 3) and coverage (H, W), default settings."""
    out = {}
    for name, path, method, options, size, spp in CASES:
        s = tr.load_scene(str(ROOT / "configs" / "suite" / path))
        cam = dataclasses.replace(s.camera, width=size, height=size, samples_per_pixel=spp)
        r = tr.render([s.replace(camera=cam, method=method, method_options=options)])
        out[name] = r.radiance[0].numpy()
        out[name + ".coverage"] = r.coverage[0].numpy()
    return out


def record() -> None:
    images = render_cases()
    DATA.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(DATA, revision=np.int64(tr.IMAGE_REVISION), **images)
    print(f"recorded {len(CASES)} images at image revision {tr.IMAGE_REVISION} in {DATA}")


@pytest.fixture(scope="module")
def kept():
    with np.load(DATA) as z:
        return {k: z[k] for k in z.files}


def test_the_images_are_recorded_at_this_revision(kept):
    assert int(kept["revision"]) == tr.IMAGE_REVISION, (
        f"tests/data/image_revision.npz holds revision {int(kept['revision'])}, the code is "
        f"at {tr.IMAGE_REVISION}: record the images again (this file's docstring)")


def test_the_default_images_are_those_of_this_revision(kept):
    now = render_cases()
    changed = []
    for name, *_ in CASES:
        ref, img = kept[name], now[name]
        cov = kept[name + ".coverage"] > 0
        assert np.array_equal(cov, now[name + ".coverage"] > 0), f"{name}: coverage changed"
        for part, where in (("object", cov), ("background", ~cov)):
            if not where.any():
                continue
            a, b = ref[where], img[where]
            mean_diff = float(np.abs(a - b).mean()) / max(float(np.abs(a).mean()), 1e-6)
            rel = np.abs(a - b).max(-1) / (np.abs(a).max(-1) + 1e-3)
            if mean_diff > 1e-3 or float(np.quantile(rel, 0.99)) > 0.02:
                changed.append(f"{name} {part} (mean {mean_diff:.2e}, 99% "
                               f"{np.quantile(rel, 0.99):.3f})")
    assert not changed, (
        f"default images changed at image revision {tr.IMAGE_REVISION}: {', '.join(changed)}. "
        "If meant, raise torchrefract.IMAGE_REVISION and record them again (this file's "
        "docstring); datasets resumed across the change are then warned.")


if __name__ == "__main__":
    if "--record" in sys.argv[1:]:
        record()
    else:
        print(__doc__)
