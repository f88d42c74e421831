"""scripts/thick_regions.py: the thickness split and the "clearly better" count (a variant
is clearly better than prefiltered on a scene only where its thick-region FLIP is lower by
more than the truth's own noise there)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("thick_regions",
                                                  ROOT / "scripts" / "thick_regions.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_region_masks_split_object_pixels_at_a_fraction_of_the_thickest():
    tr = _script()
    cov = np.array([[1.0, 1.0, 1.0, 0.0]])
    thick = np.array([[0.2, 0.5, 1.0, 5.0]])  # the background's thickness is ignored
    m = tr.region_masks(cov, thick, 0.5)
    assert m["all"].tolist() == [[True, True, True, False]]
    assert m["thick"].tolist() == [[False, True, True, False]]
    assert m["thin"].tolist() == [[True, False, False, False]]


def _row(scene, noise, pre, **others):
    return {"scene": scene, "noise": {"thick": {"flip": noise}},
            "variants": {"prefiltered": {"thick": {"flip": pre}},
                         **{k: {"thick": {"flip": v}} for k, v in others.items()}}}


def test_clearly_better_counts_only_differences_beyond_the_truth_noise():
    tr = _script()
    rows = [_row("a", 0.03, 0.30, r=0.20, k=0.29),  # r better by 0.10; k within noise
            _row("b", 0.05, 0.30, r=0.26, k=0.40),  # r within noise; k worse by 0.10
            _row("c", 0.02, 0.10, r=0.05, k=0.07)]  # both better than the 0.02 noise
    lines = tr.clearly_better(rows, "prefiltered", ["r", "k"])
    assert lines[-1] == "| clearly better / worse | | | 2 / 0 of 3 | 1 / 1 of 3 |"
    assert "| a | 0.030 | 0.300 | 0.200 (-0.100) | 0.290 (-0.010) |" in lines
