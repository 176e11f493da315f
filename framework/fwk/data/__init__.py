"""Data layer: Template, MeshCollection, mesh io, preprocessing and splits."""
from .template import UNITS, MeshCollection, Template, Units, check_units

__all__ = ["Template", "MeshCollection", "UNITS", "Units", "check_units"]
