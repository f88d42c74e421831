"""Method ``sh``: Genevaux et al. 2006, Interactive Refraction on Complex Static Geometry
using Spherical Harmonics, for rough glass as well as smooth.

Offline, once per mesh and IOR (``prepare``; :mod:`.precompute`, cached by :mod:`.cache`):
view rays are traced through the real mesh from surface samples (:mod:`.layout`) over the
outer hemisphere of directions (:mod:`.basis`), each following the refracted branch at
every interface, the reflected one under TIR (``branch: tir``) or wherever Fresnel makes it
the most significant (``branch: greedy``, the paper's) (:mod:`.paths`, with Embree or Mitsuba:
:mod:`.tracer`); exit direction, length inside, exit cosine and throughput are compressed
per sample into real spherical harmonics up to band 8 (eqs. 3-10, mirrored hemisphere);
with ``branches: 2`` also those of the Fresnel-reflected branch at each path's first
refraction out from inside.

Per frame (``shade``; :mod:`.shade`): the front hit and the view direction read the
mapping (eq. 2, SH order and ringing window of sec. 4.3 as options), the environment is
looked up around the exit direction with a lobe as wide as the entry's and the exit's
roughness make it (the shared SG lobe code), the front Fresnel reflection is added, sphere
lights and absorption (sec. 5.4) included.

Static by design: the table belongs to the mesh's content (object space); any rigid pose
and uniform scale of that mesh reuse it, a changed mesh is precomputed anew, and a G-buffer
whose mesh is not the prepared one is refused (never a silently wrong image). Choices and
measurements: docs/decisions_sh.md.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from torchrefract.geometry.mesh import load_mesh
from torchrefract.methods.base import Method, Shaded
from torchrefract.methods.sh.cache import get_table
from torchrefract.methods.sh.options import SHOptions
from torchrefract.methods.sh.precompute import Settings
from torchrefract.methods.sh.shade import SceneTable, render_sh, scene_table
from torchrefract.settings import cache_folder


def prepare_tables(scenes: Sequence, options: SHOptions) -> tuple[SceneTable, ...]:
    """Per scene, the precomputed mapping of its mesh at its IOR (loaded or computed and
    cached: :func:`.cache.get_table`) and its transform."""
    out = []
    for s in scenes:
        mesh = load_mesh(s.mesh)  # object space: the table is pose-independent
        ior = float(np.float32(s.material.ior))
        table = None
        if ior != 1.0:
            settings = Settings(ior=ior, rings=options.view_rings,
                                samples=options.surface_samples, max_events=options.max_bounces,
                                branch=options.branch, branches=options.branches)
            table, _ = get_table(mesh, settings, cache_folder(), options.tracer,
                                 name=str(s.mesh).rsplit("/", 1)[-1])
        out.append(scene_table(table, mesh, s.transform))
    return tuple(out)


class SH(Method):
    """Precomputed refracted-path mapping in spherical harmonics (package docstring)."""

    name = "sh"
    devices = ("cpu",)  # its precomputed state is CPU tensors (not moved yet)
    Options = SHOptions

    def prepare(self, scenes, options):
        return prepare_tables(scenes, options)

    def shades_samples(self, options, materials) -> bool:
        # each sample's own front hit and view direction read the table (eq. 2); nothing
        # is marched and no neighbour is read
        return True

    def strips(self, scenes, options) -> str | None:
        return None  # a roughness map too: read at each pixel's front hit

    def shade(self, g, lighting, materials, options, state) -> Shaded:
        return Shaded(*render_sh(g, lighting, materials, options, state))


METHOD = SH()

__all__ = ["METHOD", "SH", "SHOptions", "prepare_tables", "render_sh"]
