"""Geometry services (float64 NumPy/SciPy): edge structures, one-rings and components, the
cotangent Laplacian (thesis eq. 4.10, positive semi-definite), mass matrices (mixed Voronoi,
Meyer et al. 2003; barycentric), face areas and vertex normals, Kabsch rigid registration, the
generalised eigenbasis (eqs. 4.1 / 4.2) and spectral projection without n x n matrices.
The torch projection for training-time use is ``fwk.geometry.spectral_torch`` (imported on
demand so that this package does not import torch)."""
from .kabsch import kabsch  # noqa: F401
from .topology import (  # noqa: F401
    EdgeTopology, border_edges, connected_components, edge_faces, edge_topology, edges, interior_edges,
    non_manifold_edges, one_ring,
)
from .operators import (  # noqa: F401
    check_mesh, cotangent_laplacian, face_areas, factor_spd, mass_matrix, vertex_normals,
)
from .spectral import SpectralProjector, ShiftedFactors, eigenbasis, generalized_eigs, has_cholmod  # noqa: F401
