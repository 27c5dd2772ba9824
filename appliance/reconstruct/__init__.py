"""Decoding (numba kernels), triangulation, filtering and the point cloud type."""

from appliance.reconstruct.types import DecodedMaps, PointCloud

__all__ = ["DecodedMaps", "PointCloud"]
