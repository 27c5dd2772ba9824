"""Camera and projector models, rays, poses and the calibration file."""

from appliance.geometry.camera import CameraModel, ProjectorModel, look_at

__all__ = ["CameraModel", "ProjectorModel", "look_at"]
