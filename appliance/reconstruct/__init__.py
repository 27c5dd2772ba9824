"""Decoding (numba kernels), triangulation, filtering and the point cloud type."""

from appliance.reconstruct.types import DecodedMaps, PointCloud

__all__ = ["DecodedMaps", "PointCloud"]

from appliance.reconstruct.decode import DecodeParams, DecodePlan, StreamingDecoder, decode, plan_decode

__all__ += ["DecodeParams", "DecodePlan", "StreamingDecoder", "decode", "plan_decode"]

from appliance.reconstruct.filters import (  # noqa: E402
    estimate_normals,
    filter_isolated,
    to_point_cloud,
)
from appliance.reconstruct.pipeline import Reconstructor  # noqa: E402
from appliance.reconstruct.stereo import StereoTriangulator, triangulate_stereo  # noqa: E402
from appliance.reconstruct.triangulate import ProjectorTriangulator  # noqa: E402

__all__ += [
    "ProjectorTriangulator",
    "Reconstructor",
    "StereoTriangulator",
    "estimate_normals",
    "filter_isolated",
    "to_point_cloud",
    "triangulate_stereo",
]
