"""Material parameters of a batch of scenes as tensors (what the methods consume)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .scene import Scene


@dataclass(frozen=True)
class MaterialBatch:
    """Materials of B scenes.

    Attributes:
        ior: (B,) index of refraction inside (outside is 1).
        roughness: (B,) microfacet alpha (clamped to >= 1e-4 where a method needs it).
        absorption: (B, 3) Beer-Lambert coefficients per unit world length.
        distribution: B names, ``beckmann`` or ``ggx``.
    """

    ior: torch.Tensor
    roughness: torch.Tensor
    absorption: torch.Tensor
    distribution: tuple[str, ...]

    @staticmethod
    def from_scenes(scenes: list[Scene]) -> "MaterialBatch":
        return MaterialBatch(
            ior=torch.tensor([s.material.ior for s in scenes], dtype=torch.float32),
            roughness=torch.tensor([s.material.roughness for s in scenes], dtype=torch.float32),
            absorption=torch.tensor([s.material.absorption for s in scenes],
                                    dtype=torch.float32),
            distribution=tuple(s.material.distribution for s in scenes),
        )
