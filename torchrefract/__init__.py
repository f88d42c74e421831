"""torchrefract: a PyTorch renderer of rough transparent objects, built for datasets.

Public API::

    scene = torchrefract.load_scene("configs/demo.yaml")
    out = torchrefract.render([scene], method="specular")
    out.radiance   # (B, H, W, 3) float32 linear RGB
    out.coverage   # (B, H, W)
    out.passes     # dict of (B, H, W, C)
    # with scene.passes = {"matte": {}}: the lobes of every pixel, relightable
    img = torchrefract.relight(out, "other_map.exr", rotate_deg=90.0)
"""

from torchrefract.checks import ConfigError
from torchrefract.heap import set_heap_reuse
from torchrefract.kernels.compiled import set_compile
from torchrefract.kernels.native import set_native
from torchrefract.matte.relight import relight
from torchrefract.methods import register_method
from torchrefract.render import render
from torchrefract.result import RenderResult
from torchrefract.scene import (
                                Camera,
                                EnvMap,
                                Material,
                                Scene,
                                SphereLight,
                                Transform,
                                load_scene,
                                scene_from_dict,
)
from torchrefract.settings import RenderSettings

__version__ = "0.1.0"

IMAGE_REVISION = 9
"""Raised by one whenever a default render's image changes (a method's result, adaptive
sampling, a default option): datasets record it per sample and in ``sweep.json``, and a
resume whose folder was begun at another revision says so (its images would mix both)."""

__all__ = ["Camera", "ConfigError", "EnvMap", "Material", "RenderResult", "RenderSettings", "Scene",
           "SphereLight", "Transform", "load_scene", "register_method", "relight", "render",
           "scene_from_dict", "set_compile", "set_heap_reuse", "set_native", "IMAGE_REVISION",
           "__version__"]
