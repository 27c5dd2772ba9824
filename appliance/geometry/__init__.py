"""Camera and projector models, rays, poses and the calibration file."""

from appliance.geometry.calibration_file import Calibration, read_calibration, write_calibration
from appliance.geometry.camera import CameraModel, ProjectorModel, look_at
from appliance.geometry.rays import RayTable

__all__ = [
    "Calibration",
    "CameraModel",
    "ProjectorModel",
    "RayTable",
    "look_at",
    "read_calibration",
    "write_calibration",
]
