"""Pattern sequences: the data model, generators, projector images and manifests."""

from appliance.patterns.manifest import Manifest, read_manifest, write_manifest
from appliance.patterns.render import frame_intensity, render_frame
from appliance.patterns.sequence import (
    Axis,
    BlackFrame,
    Frame,
    GrayFrame,
    OtherFrame,
    PhaseFrame,
    Sequence,
    WhiteFrame,
    gray_bits_needed,
    gray_code_frames,
    gray_code_sequence,
    gray_phase_sequence,
    phase_shift_frames,
)

__all__ = [
    "Axis",
    "BlackFrame",
    "Frame",
    "GrayFrame",
    "Manifest",
    "OtherFrame",
    "PhaseFrame",
    "Sequence",
    "WhiteFrame",
    "frame_intensity",
    "gray_bits_needed",
    "gray_code_frames",
    "gray_code_sequence",
    "gray_phase_sequence",
    "phase_shift_frames",
    "read_manifest",
    "render_frame",
    "write_manifest",
]
