"""The exit rule: what leaves at the last interface a method follows, under total internal
reflection and beside it (``tir`` in ``method_options``).

- ``conserve`` (default; ours): the part the interface reflects inside (all of it under TIR)
  leaves there too, times the fraction of trapped light that eventually escapes
  (:func:`torchrefract.shading.bounces.escape_fraction`; 1 for smooth glass): continuous at
  the critical angle, and smooth glass keeps its energy in a white furnace.
- ``clamp`` (Wyman 2005's and de Rousiers 2012's choice): under TIR all that the interface
  keeps leaves at the critical angle; outside TIR the internal reflection is lost.
- ``reflect``: under TIR the light is reflected once and leaves along the mirror direction
  (the caller sets the direction).
"""

from __future__ import annotations

import torch

TIR_RULES = ("conserve", "clamp", "reflect")

CRITICAL_MARGIN = 1e-4
"""How far short of the critical angle (in cosine) a lobe clamped to it is looked up: just
outside TIR, where the table's transmitted lobe still exists."""


def critical_cosine(ior: torch.Tensor) -> torch.Tensor:
    """cos theta_c = sqrt(1 - 1 / ior^2) of light leaving the glass (0 for ior <= 1; its
    gradient there 0, not sqrt's infinite slope at 0 times the clamp's: NaN at ior 1)."""
    x = 1.0 - 1.0 / (ior * ior)
    inside = x > 0.0
    return torch.where(inside, torch.sqrt(torch.where(inside, x, torch.ones_like(x))),
                       torch.zeros_like(x))


def clamp_to_critical(cos: torch.Tensor, tir: torch.Tensor, cos_crit: torch.Tensor
                      ) -> torch.Tensor:
    """The incident cosine a lobe leaves with under ``clamp`` and ``conserve``: under TIR
    the critical angle's (Wyman 2005; de Rousiers 2012 sec. 4.3), elsewhere ``cos``."""
    return torch.where(tir, cos_crit + CRITICAL_MARGIN, cos)


def leaving_weight(tir_mode: str, tir: torch.Tensor, e_t: torch.Tensor,
                   e_r: torch.Tensor | None = None, esc: torch.Tensor | None = None,
                   kept: torch.Tensor | None = None) -> torch.Tensor:
    """The weight of the light leaving the last interface under the ``tir`` rule (module
    docstring), from the interface's transmitted and reflected energies ``e_t``, ``e_r``.

    ``conserve``: e_t + e_r esc (at most 1; ``esc``:
    :func:`torchrefract.shading.bounces.escape_fraction`); ``reflect``: under TIR e_r (the
    caller sets the mirror direction); ``clamp``: under TIR ``kept``, what the interface
    keeps, by default e_t + e_r (at most 1; ``rousiers``' cone-traced exit passes 1, the
    paper's rule: all the light leaves at the critical angle). Outside TIR ``reflect`` and
    ``clamp`` give e_t.
    """
    if tir_mode == "conserve":
        return (e_t + e_r * esc).clamp(max=1.0)
    if tir_mode == "reflect":
        return torch.where(tir, e_r, e_t)
    return torch.where(tir, (e_t + e_r).clamp(max=1.0) if kept is None else kept, e_t)


def last_interface(tir_mode: str, tir: torch.Tensor, e_t: torch.Tensor, e_r: torch.Tensor,
                   esc: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``tir`` rule at the last interface followed (module docstring): the weight of the
    light leaving there (:func:`leaving_weight`), and the reflected part that does not (the
    residual: none under ``conserve``; under TIR none under ``reflect`` and ``clamp``, where
    it leaves).
    """
    zero = torch.zeros_like(e_t)
    weight = leaving_weight(tir_mode, tir, e_t, e_r, esc)
    if tir_mode == "conserve":
        return weight, zero
    return weight, torch.where(tir, zero, e_r)


__all__ = ["CRITICAL_MARGIN", "TIR_RULES", "clamp_to_critical", "critical_cosine",
           "last_interface", "leaving_weight"]
