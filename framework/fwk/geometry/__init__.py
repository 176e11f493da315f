"""Geometry services (float64 NumPy/SciPy): edge structures, rigid registration, and (see the
geometry issue) Laplacians, mass matrices and spectral bases."""
from .kabsch import kabsch  # noqa: F401
from .topology import EdgeTopology, edge_topology  # noqa: F401
