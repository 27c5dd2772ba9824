"""Reconstruction defaults read off a calibration: the depth range its devices can see together.

:func:`depth_range_from_geometry` picks the device pairs a calibration triangulates with (every camera with
the projector; without a projector, the first camera with the second) and returns the union of their
common fields of view along the camera rays, as computed by
:func:`appliance.reconstruct.defaults.default_depth_range_mm` (frustum overlap with a minimum
triangulation angle, widened by a margin).
"""

from __future__ import annotations

from typing import Literal

from appliance.errors import CalibrationError
from appliance.geometry.calibration_file import Calibration
from appliance.reconstruct.defaults import default_depth_range_mm


def depth_range_from_geometry(
    calibration: Calibration, mode: Literal["auto", "projector", "stereo", "both"] = "auto"
) -> tuple[float, float]:
    """Depth range (mm, camera frame) in which the calibrated rig can triangulate.

    Parameters
    ----------
    calibration : Calibration
        Cameras (and projector) with their poses.
    mode : {'auto', 'projector', 'stereo', 'both'}
        Which pairs count: ``'projector'`` every camera with the projector, ``'stereo'`` the first camera
        with the second, ``'both'`` all of those (the union of their ranges), ``'auto'`` the projector pairs
        when there is a projector, else the stereo pair.

    Returns
    -------
    (z_min, z_max) : tuple of float
        Nearest and farthest depth (mm) at which some pixel of a camera sees into the other device's
        image with a usable triangulation angle.

    Raises
    ------
    CalibrationError
        When the calibration lacks the devices of the mode, or they see no common volume.
    """
    cams = calibration.cameras
    proj = calibration.projector
    if mode == "both":
        near_p, far_p = depth_range_from_geometry(calibration, "projector")
        near_s, far_s = depth_range_from_geometry(calibration, "stereo")
        return min(near_p, near_s), max(far_p, far_s)
    if mode == "auto":
        mode = "projector" if proj is not None else "stereo"
    if mode == "projector":
        if proj is None or not cams:
            raise CalibrationError(
                f"calibration: depth range for camera-projector needs a camera and a 'projector'; it has "
                f"{sorted(calibration.devices)}: add the projector's calibration or use mode stereo"
            )
        return default_depth_range_mm(cams, [proj])
    if len(cams) < 2:
        raise CalibrationError(
            f"calibration: depth range for camera-camera needs two cameras; it has {calibration.camera_names}"
        )
    return default_depth_range_mm(cams[:1], cams[1:2])
