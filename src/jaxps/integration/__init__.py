"""Integration: from a normal field to a height map, and back.

Takes `(H, W, 3)` normals (and a mask, a method name, optionally camera intrinsics); gives an
`(H, W)` height map by Frankot–Chellappa, DCT Poisson, masked least squares or
discontinuity-aware (bilateral) integration, with integrability diagnostics, and normals
re-derived from a height map.
"""

from ._integrate import (
    INTEGRATION_METHODS,
    IntegrationResult,
    gradients_from_normals,
    integrability_map,
    integrate,
    normals_from_height,
)

__all__ = [
    "INTEGRATION_METHODS",
    "IntegrationResult",
    "gradients_from_normals",
    "integrability_map",
    "integrate",
    "normals_from_height",
]
