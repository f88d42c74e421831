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


def last_interface(tir_mode: str, tir: torch.Tensor, e_t: torch.Tensor, e_r: torch.Tensor,
                    esc: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``tir`` rule at the last interface followed (module docstring): the weight of the
    light leaving there, and the reflected part that does not (the residual).

    ``conserve``: the reflected part leaves too, after the losses of the bounces not
    followed (``esc``, :func:`torchrefract.shading.bounces.escape_fraction`; 1 when smooth), so the
    weight is continuous at TIR; ``reflect``: under TIR the reflected light leaves (along
    the mirror direction, which the caller sets); ``clamp``: under TIR all the interface
    keeps leaves at the critical angle.
    """
    zero = torch.zeros_like(e_t)
    if tir_mode == "conserve":
        return (e_t + e_r * esc).clamp(max=1.0), zero
    if tir_mode == "reflect":
        return torch.where(tir, e_r, e_t), torch.where(tir, zero, e_r)
    return torch.where(tir, (e_t + e_r).clamp(max=1.0), e_t), torch.where(tir, zero, e_r)


__all__ = ["TIR_RULES", "last_interface"]
