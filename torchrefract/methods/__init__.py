"""Rendering methods: each one a :class:`~torchrefract.methods.base.Method`, found by name
through :mod:`torchrefract.methods.registry` (imported only when used)."""

from torchrefract.methods.registry import get, is_policy, method_names, register_method

__all__ = ["get", "is_policy", "method_names", "register_method"]
