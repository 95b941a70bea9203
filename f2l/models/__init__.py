"""Lighting models: the plugin interface and the entry-point registry."""

from f2l.models.base import LightingModel
from f2l.models.registry import GROUP, ModelNotFoundError, discover, load_model

__all__ = ["GROUP", "LightingModel", "ModelNotFoundError", "discover", "load_model"]
