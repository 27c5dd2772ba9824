"""Every triangulation kernel under its old module path (private).

The kernels live by concern in ``_procam_kernels`` (camera-projector), ``_stereo_kernels`` (camera-camera),
``_filter_kernels`` (filters, cloud assembly), ``_normal_kernels`` (normals) and ``_geom_kernels`` (shared).
"""

from appliance.reconstruct._filter_kernels import (
    apply_keep,
    compact,
    filter_depth,
    filter_quality,
    isolated_keep,
    row_counts,
)
from appliance.reconstruct._geom_kernels import distort_jac
from appliance.reconstruct._normal_kernels import normals
from appliance.reconstruct._procam_kernels import (
    code_line_table,
    depth_filtered,
    emit_points,
    epipolar_intercepts,
    organised_from_depth,
    tri_plane,
    tri_ray,
)
from appliance.reconstruct._stereo_kernels import project_dirs, remap_codes

__all__ = [
    "apply_keep", "code_line_table", "compact", "depth_filtered", "distort_jac", "emit_points",
    "epipolar_intercepts", "filter_depth", "filter_quality", "isolated_keep", "normals", "organised_from_depth",
    "project_dirs", "remap_codes", "row_counts", "tri_plane", "tri_ray",
]
