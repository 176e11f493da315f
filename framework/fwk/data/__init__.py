"""Data layer: Template, MeshCollection, mesh io, preprocessing and splits."""
from .template import MeshCollection, Template

__all__ = ["Template", "MeshCollection"]
