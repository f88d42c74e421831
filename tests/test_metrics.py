"""HDR-FLIP in torchrefract.truth.metrics: FLIP's own exposure rule, the degenerate references that
make FLIP exit the process, masks, and the ``compare`` / ``torchrefract compare`` outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from torchrefract.cli import main
from torchrefract.output.images import write_exr
from torchrefract.truth.metrics import compare, flip_map, hdr_flip_exposures, hdr_flip_map

flip_evaluator = pytest.importorskip("flip_evaluator")


def _hdr_image(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    """A smooth HDR image (0.05 .. ~6) with a bright highlight blob above 1."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    base = 0.05 + 0.6 * xx[..., None] * np.array([1.0, 0.8, 0.6]) + 0.2 * yy[..., None]
    blob = 5.0 * np.exp(-(((xx - 0.6) ** 2 + (yy - 0.4) ** 2) / 0.01))[..., None]
    img = base + blob + 0.01 * rng.random((h, w, 3))
    return img.astype(np.float32)


def test_exposures_match_flips_automatic_rule():
    ref = _hdr_image()
    test = ref * 1.2
    _, mean_auto, params = flip_evaluator.evaluate(ref, test, "HDR", applyMagma=False)
    ours = hdr_flip_exposures(ref)
    assert ours["startExposure"] == pytest.approx(params["startExposure"], abs=1e-5)
    assert ours["stopExposure"] == pytest.approx(params["stopExposure"], abs=1e-5)
    assert ours["numExposures"] == params["numExposures"]
    assert hdr_flip_map(test, ref).mean() == pytest.approx(mean_auto, rel=1e-5)


def test_hdr_flip_zero_on_equal_grows_with_error_and_sees_highlights():
    ref = _hdr_image()
    assert hdr_flip_map(ref, ref).max() == 0.0
    small, large = hdr_flip_map(ref * 1.05, ref).mean(), hdr_flip_map(ref * 1.5, ref).mean()
    assert 0.0 < small < large
    # Highlights above 1: the 8-bit preview clips both to white, HDR-FLIP does not.
    hi = ref > 1.0
    assert hi.any(-1).mean() > 0.02
    brighter = np.where(hi, ref * 1.5, ref)
    px = hi.any(-1)
    assert flip_map(brighter, ref)[px].mean() < 0.02
    assert hdr_flip_map(brighter, ref)[px].mean() > 0.05


def test_degenerate_references_do_not_exit():
    # FLIP itself calls exit() on these (start exposure > stop exposure or NaN).
    black = np.zeros((32, 32, 3), np.float32)
    assert hdr_flip_map(black, black).max() == 0.0
    assert 0.5 < hdr_flip_map(np.ones_like(black), black).mean() <= 1.0
    mostly_black = black.copy()
    mostly_black[:8] = 2.0  # median luminance 0
    e = hdr_flip_map(mostly_black * 1.3, mostly_black)
    assert np.isfinite(e).all() and e[:8].mean() > 0.0 and e[16:].max() == 0.0
    nan = mostly_black.copy()
    nan[0, 0] = np.nan
    assert np.isfinite(hdr_flip_map(nan, mostly_black)).all()


def test_compare_has_hdr_flip_whole_image_and_object():
    ref = _hdr_image()
    x = ref.copy()
    x[:, :32] *= 1.4  # error only on the left half
    cov = np.zeros(ref.shape[:2], np.float32)
    cov[:, :32] = 1.0  # the "object" is the left half
    m = compare(x, ref, cov)
    e = hdr_flip_map(x, ref)
    assert m["hdrflip"] == pytest.approx(e.mean())
    assert m["hdrflip_object"] == pytest.approx(e[:, :32].mean())
    assert m["hdrflip_object"] > m["hdrflip"] > 0.0
    assert compare(ref, ref, cov)["hdrflip_object"] == 0.0


def test_cli_compare_prints_hdr_flip(tmp_path, capsys):
    ref, x = _hdr_image(), _hdr_image() * 1.3
    for name, img in (("ref", ref), ("x", x)):
        write_exr(tmp_path / f"{name}.exr", {"R": img[..., 0], "G": img[..., 1],
                                             "B": img[..., 2], "A": np.ones(img.shape[:2],
                                                                            np.float32)})
    js = tmp_path / "m.json"
    assert main(["compare", str(tmp_path / "x.exr"), str(tmp_path / "ref.exr"),
                 "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "hdrflip " in out and "hdrflip_object " in out
    m = json.loads(js.read_text())
    assert m["hdrflip"] == pytest.approx(hdr_flip_map(x, ref).mean(), rel=1e-5)
