"""The scene description: the YAML model of SCENE_SPEC.md and its strict loader."""

from torchrefract.scene.loader import load_scene, scene_from_dict, validate
from torchrefract.scene.model import Camera, EnvMap, Material, Scene, SphereLight, Transform

__all__ = ["Camera", "EnvMap", "Material", "Scene", "SphereLight", "Transform", "load_scene",
           "scene_from_dict", "validate"]
