"""Material parameters of a batch of scenes as tensors (what the methods consume)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchrefract.kernels import native
from torchrefract.kernels.index import put_, take, where_in
from torchrefract.optics.textures import load_roughness_map
from torchrefract.scene.model import Scene


@dataclass(frozen=True)
class MaterialBatch:
    """Materials of B scenes.

    Attributes:
        ior: (B,) index of refraction inside (outside is 1).
        roughness: (B,) microfacet alpha (clamped to >= 1e-4 where a method needs it).
        absorption: (B, 3) Beer-Lambert coefficients per unit world length.
        distribution: B names, ``beckmann`` or ``ggx``.
        roughness_maps: B (H, W) maps in [0, 1] over the UVs, or None (uniform roughness).
        roughness_range: (B, 2) a map value v means alpha = lo + v (hi - lo).
    """

    ior: torch.Tensor
    roughness: torch.Tensor
    absorption: torch.Tensor
    distribution: tuple[str, ...]
    roughness_maps: tuple[torch.Tensor | None, ...] = ()
    roughness_range: torch.Tensor | None = None

    def distribution_index(self) -> torch.Tensor:
        """(B,) long: 0 for beckmann, 1 for ggx (the SG table's distribution axis)."""
        return torch.tensor([{"beckmann": 0, "ggx": 1}[d] for d in self.distribution])

    @property
    def has_maps(self) -> bool:
        return any(m is not None for m in self.roughness_maps)

    def roughness_at(self, batch: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        """Per-point roughness (N,) of points on scene ``batch`` (N,) at UVs (N, 2)."""
        from torchrefract.optics.textures import sample_uv  # noqa: PLC0415

        if self.has_maps:  # the same values in one kernel call, where it runs
            out = native.roughness_at(self.roughness, self.roughness_maps,
                                      self.roughness_range, batch, uv)
            if out is not None:
                return out
        alpha = take(self.roughness, batch)  # a new tensor (index_select copies)
        # one lookup per map (a sweep's views share the loaded one), each point with its
        # view's range: per point the same values as a lookup per view
        views: dict[int, list[int]] = {}
        for b, tex in enumerate(self.roughness_maps):
            if tex is not None:
                views.setdefault(id(tex), []).append(b)
        for group in views.values():
            sel = where_in(batch, group, len(self.roughness_maps))
            if sel.numel():
                lo, hi = take(self.roughness_range, take(batch, sel)).unbind(-1)
                tex = self.roughness_maps[group[0]]
                put_(alpha, sel, lo + sample_uv(tex, take(uv, sel)) * (hi - lo))
        return alpha

    @staticmethod
    def from_scenes(scenes: list[Scene]) -> "MaterialBatch":
        return MaterialBatch(
            ior=torch.tensor([s.material.ior for s in scenes], dtype=torch.float32),
            roughness=torch.tensor([s.material.roughness for s in scenes], dtype=torch.float32),
            absorption=torch.tensor([s.material.absorption for s in scenes],
                                    dtype=torch.float32),
            distribution=tuple(s.material.distribution for s in scenes),
            roughness_maps=tuple(None if s.material.roughness_map is None
                                 else load_roughness_map(s.material.roughness_map)
                                 for s in scenes),
            roughness_range=torch.tensor([s.material.roughness_range for s in scenes],
                                         dtype=torch.float32),
        )
