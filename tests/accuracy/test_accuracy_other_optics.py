"""Accuracy on virtual-rig renders we did not tune to (issue 8 item 9).

Other optics than the default rig (a 1440 x 1080 camera with 2000 px focal length, an off-centre principal
point and strong distortion; a projector with 1900 px focal length on the other side, raised, 170 mm away),
another scene (tilted plane, sphere and a tilted cylinder with 30-50 % albedo texture), other photometry
(dimmer projector, more ambient light, 1.5 DN read noise with 30 e-/DN shot noise, more projector and camera
defocus) and both axes coded (ray-ray triangulation), reconstructed with the product's defaults apart from
the depth range, the camera noise and a sigma limit of 1 mm. Targets: RMS <= 0.13 mm, median <= 0.08 mm,
fewer than 0.005 % of points over 1 mm, >= 98 % of the lit pixels reconstructed.
"""

from __future__ import annotations

from appliance.config.schema import (
    CylinderObject,
    DeviceOptics,
    ImagingConfig,
    PlaneObject,
    ReconstructionConfig,
    SphereObject,
    VirtualRigConfig,
)
from appliance.patterns.sequence import gray_phase_sequence
from appliance.reconstruct.decode import DecodeParams, decode
from appliance.reconstruct.pipeline import Reconstructor
from appliance.scan import virtual_calibration
from appliance.sim.accuracy import compare_to_ground_truth
from appliance.sim.rig import VirtualRig

READ_NOISE_DN, ELECTRONS_PER_DN = 1.5, 30.0


def _rig() -> VirtualRig:
    camera = DeviceOptics(width=1440, height=1080, focal_px=2000.0, principal_px=(731.0, 528.5),
                          dist=(-0.22, 0.16, 0.0012, -0.0009, -0.04), look_at_mm=(0.0, 0.0, 700.0))  # fmt: skip
    projector = DeviceOptics(width=1280, height=800, focal_px=1900.0, dist=(0.05, -0.03, 0.0, 0.0, 0.0),
                             position_mm=(-160.0, 45.0, 15.0), look_at_mm=(0.0, 0.0, 700.0))  # fmt: skip
    scene = (
        PlaneObject(point_mm=(0.0, 0.0, 760.0), normal=(0.15, -0.05, -1.0), albedo=0.7, texture=0.5),
        SphereObject(center_mm=(35.0, -15.0, 690.0), radius_mm=50.0, albedo=0.9, texture=0.4),
        CylinderObject(
            center_mm=(-80.0, 20.0, 700.0), axis=(0.1, 1.0, 0.2), radius_mm=25.0, height_mm=120.0, texture=0.3
        ),
    )
    imaging = ImagingConfig(
        projector_gain_dn=150.0, ambient_dn=20.0, read_noise_dn=READ_NOISE_DN, electrons_per_dn=ELECTRONS_PER_DN,
        projector_blur_px=0.9, camera_blur_px=0.6, seed=23,
    )  # fmt: skip
    return VirtualRig(VirtualRigConfig(cameras={"cam0": camera}, projector=projector, scene=scene, imaging=imaging))


def test_other_optics_both_axes_meet_the_accuracy_targets() -> None:
    rig = _rig()
    seq = gray_phase_sequence(rig.projector.width, rig.projector.height, "xy", period=8, steps=8)
    frames = rig.render(seq, "cam0")
    maps = decode(frames, seq, DecodeParams())
    cfg = ReconstructionConfig(min_depth_mm=400, max_depth_mm=1100, camera_read_noise_dn=READ_NOISE_DN,
                               camera_electrons_per_dn=ELECTRONS_PER_DN, max_sigma_mm=1.0)  # fmt: skip
    rec = Reconstructor(virtual_calibration(rig), "xy", cfg, sequence=seq).run({"cam0": maps}, {"cam0": frames[0]})
    cloud = rec.cloud
    rep = compare_to_ground_truth(cloud, rig, ["cam0"])
    print(rep.line(), rec.stages[0].rejected())
    assert rep.points > 900_000
    assert rep.rms_mm <= 0.13
    assert rep.median_mm <= 0.08
    assert rep.share_over_1mm < 5e-5
    assert rep.completeness >= 0.98
    assert not rec.warnings
