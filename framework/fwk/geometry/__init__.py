"""Geometry services (float64 NumPy/SciPy): edge structures, rigid registration, and (see the
geometry issue) Laplacians, mass matrices and spectral bases."""
from .kabsch import kabsch  # noqa: F401
from .topology import EdgeTopology, connected_components, edge_topology, one_ring  # noqa: F401
from .operators import check_mesh, cotangent_laplacian, mass_matrix  # noqa: F401
from .spectral import SpectralProjector, eigenbasis, generalized_eigs  # noqa: F401
