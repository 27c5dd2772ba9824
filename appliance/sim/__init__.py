"""The virtual rig: a known scene seen by ground-truth cameras under a simulated projector."""

from appliance.sim.render import FrameRenderer, projected_light
from appliance.sim.rig import GroundTruth, VirtualRig, device_model
from appliance.sim.scene import PlaneImageAlbedo, ProceduralAlbedo, RayHits, Scene, icosphere, load_mesh

__all__ = [
    "FrameRenderer",
    "GroundTruth",
    "PlaneImageAlbedo",
    "ProceduralAlbedo",
    "RayHits",
    "Scene",
    "VirtualRig",
    "device_model",
    "icosphere",
    "load_mesh",
    "projected_light",
]
