"""The virtual rig's hard physics: exposure and projector intensity, saturation, specular lobes, albedo patches,
planar mirrors (one-bounce light from a mirrored projector), and the sim camera's exposure between passes.

Small renders (a 160x128 camera); each effect is checked against the truth it must follow.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from appliance.config import parse_config
from appliance.config.backends import SimCameraConfig
from appliance.errors import ApplianceError, ConfigError
from appliance.hardware.sim import SimCamera, SimProjector, SimWorld
from appliance.patterns.sequence import BlackFrame, GrayFrame, Sequence, WhiteFrame
from appliance.sim.rig import VirtualRig

CAM = "cam0: {width: 160, height: 128, focal_px: 300, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}"
PLANE = "- {type: plane, point_mm: [0, 0, 630], normal: [0, 0.1, -1], albedo: 0.5}"
GROOVE = """
    - {type: mesh, albedo: 0.15, material: {mirror: %(mirror)s},
       vertices_mm: [[-70, -90, 590], [0, -90, 660], [0, 90, 660], [-70, 90, 590]], triangles: [[0, 1, 2], [0, 2, 3]]}
    - {type: mesh, albedo: 0.9,
       vertices_mm: [[0, -90, 660], [70, -90, 590], [70, 90, 590], [0, 90, 660]], triangles: [[0, 1, 2], [0, 2, 3]]}
"""


def _rig(scene: str, imaging: str = "read_noise_dn: 0, shot_noise: false, ambient_dn: 0, seed: 1") -> VirtualRig:
    text = f"virtual_rig:\n  cameras:\n    {CAM}\n  scene:\n    {scene}\n  imaging: {{{imaging}}}\n"
    return VirtualRig(parse_config(text, "rig.yaml").virtual_rig)


def _white(rig: VirtualRig, **kw: float) -> np.ndarray:
    return rig.render_frame(WhiteFrame(), "cam0", **kw).astype(np.float64)  # type: ignore[arg-type]


def test_exposure_scales_all_light_and_intensity_only_the_projector_s() -> None:
    rig = _rig(PLANE, "read_noise_dn: 0, shot_noise: false, projector_gain_dn: 100, ambient_dn: 20, seed: 1")
    lit = rig.ground_truth("cam0").lit & (_white(rig) > 30)
    base = rig.render_clean(WhiteFrame(), "cam0")[lit].astype(np.float64)
    amb = rig.render_clean(BlackFrame(), "cam0")[lit].astype(np.float64)
    # twice the exposure: twice the DN (rounded), until the sensor clips at 255
    np.testing.assert_allclose(_white(rig, exposure_us=20_000)[lit], np.minimum(np.round(2 * base), 255), atol=1)
    # half the projector intensity: the ambient stays, the projector's light halves
    np.testing.assert_allclose(_white(rig, intensity=0.5)[lit], np.round(amb + 0.5 * (base - amb)), atol=1)
    # 8x: the plane (albedo 0.5, ~55 DN at 1x) saturates at the 8-bit full scale and no higher
    assert (_white(rig, exposure_us=80_000)[lit] == 255).mean() > 0.9


def test_saturation_at_the_bit_depth() -> None:
    rig = _rig(PLANE, "read_noise_dn: 0, shot_noise: false, bit_depth: 12, projector_gain_dn: 700, seed: 1")
    img = rig.render_frame(WhiteFrame(), "cam0")
    assert img.dtype == np.uint16 and img.max() == 4095
    assert (img[rig.ground_truth("cam0").lit] == 4095).mean() > 0.9


def test_configured_exposure_and_a_bad_one() -> None:
    low = _rig(PLANE, "read_noise_dn: 0, shot_noise: false, ambient_dn: 0, exposure_us: 5000, seed: 1")
    ref = _rig(PLANE)
    lit = ref.ground_truth("cam0").lit
    np.testing.assert_allclose(_white(low)[lit], np.round(ref.render_clean(WhiteFrame(), "cam0")[lit] / 2), atol=1)
    with pytest.raises(ConfigError, match="exposure_us = -1"):
        low.render_frame(WhiteFrame(), "cam0", exposure_us=-1)


def test_a_specular_lobe_scales_the_same_projector_pixel_and_saturates() -> None:
    matte = "- {type: sphere, center_mm: [0, 0, 600], radius_mm: 60, albedo: 0.1}"
    sphere = matte[:-1] + ", material: {specular: 8, shininess: 80}}"
    shiny, dull = _rig(sphere), _rig(matte)
    gt = shiny.ground_truth("cam0")
    ws, wd = _white(shiny), _white(dull)
    assert ws.max() == 255 and wd.max() < 30  # a highlight clips; the diffuse part alone is dark
    # the half vector of camera and projector: the highlight lies where the normal bisects them
    x = gt.xyz[gt.lit]
    v = -x / np.linalg.norm(x, axis=1)[:, None]
    p = shiny.projector.center - x
    h = v + p / np.linalg.norm(p, axis=1)[:, None]
    h /= np.linalg.norm(h, axis=1)[:, None]
    cos_h = np.sum(gt.normal[gt.lit] * h, axis=1)
    assert cos_h[ws[gt.lit] == 255].min() > 0.95
    # a Gray frame: the lobe scales the light of the same projector pixel (no light where the bit is dark)
    frame = GrayFrame(axis="x", bit=3, stripe=16)
    gs = shiny.render_frame(frame, "cam0").astype(np.float64)
    gd = dull.render_frame(frame, "cam0").astype(np.float64)
    dark = gt.lit & (gd <= 1) & (ws == 255)
    assert dark.sum() > 5 and gs[dark].max() <= 1


def test_albedo_patches_cover_their_squares() -> None:
    rig = _rig("- {type: plane, point_mm: [0, 0, 630], material: {patches: [0.02, 0.9, 0.4], patch_mm: 25}}")
    pts = np.array([[1.0, 1.0, 630.0], [26.0, 1.0, 630.0], [51.0, 1.0, 630.0], [1.0, 26.0, 630.0], [-1.0, 1.0, 630]])
    ids = np.zeros(len(pts), np.int32)
    # index (ix + 3 iy) mod 3: (0,0) -> 0, (1,0) -> 1, (2,0) -> 2, (0,1) -> 0, (-1,0) -> 2
    np.testing.assert_allclose(rig.scene.albedo(pts, ids), [0.02, 0.9, 0.4, 0.02, 0.4])


def test_a_mirror_must_be_planar() -> None:
    with pytest.raises(ApplianceError, match=r"scene\[0\].material.mirror = 0.5: a mirror must be planar"):
        _rig("- {type: sphere, center_mm: [0, 0, 600], radius_mm: 60, material: {mirror: 0.5}}")


def test_a_mirror_face_lights_the_other_face_with_a_second_copy_of_the_pattern() -> None:
    plain, mirror = _rig(GROOVE % {"mirror": 0.0}), _rig(GROOVE % {"mirror": 0.6})
    gt = mirror.ground_truth("cam0")
    right = gt.lit & (gt.object_id == 1)
    left = gt.lit & (gt.object_id == 0)
    extra = _white(mirror) - _white(plain)
    assert (extra[right] > 5).mean() > 0.3  # the mirrored projector adds light on the matte face
    assert (extra[left] > 5).mean() > 0.3  # and the camera sees the lit matte face in the mirror
    # the added light carries the pattern of other projector pixels: a Gray frame dark at a pixel's own
    # coordinate is lit on the right face where the mirrored projector's coordinate falls in a bright stripe
    frame = GrayFrame(axis="x", bit=3, stripe=1)
    own_dark = right & (plain.render_frame(frame, "cam0") <= 1)
    ghost = mirror.render_frame(frame, "cam0").astype(np.float64)
    assert (ghost[own_dark] > 5).mean() > 0.2
    # the truth stays the direct geometry: the mirror changes light, not where the surface is
    np.testing.assert_array_equal(gt.xyz, plain.ground_truth("cam0").xyz)


def test_the_sim_camera_honours_an_exposure_set_between_passes() -> None:
    rig = _rig(PLANE)
    world = SimWorld(rig)
    cam = SimCamera("cam0", SimCameraConfig(), world)
    proj = SimProjector(world)
    seq = Sequence(1280, 800, (WhiteFrame(),))
    out = np.zeros((2, 128, 160), np.uint8)

    async def two_passes() -> None:
        await cam.open()
        await proj.load(seq)
        for k, exposure in enumerate((10_000, 5_000)):
            await cam.set_exposure(exposure)
            await cam.arm(1, out[k:k + 1])
            await proj.start()
            await cam.wait_frames(5.0)
        await cam.close()

    asyncio.run(two_passes())
    lit = rig.ground_truth("cam0").lit
    np.testing.assert_allclose(out[1][lit].astype(float), np.round(rig.render_clean(WhiteFrame(), "cam0")[lit] / 2),
                               atol=1)
    np.testing.assert_allclose(out[0][lit].astype(float), np.round(rig.render_clean(WhiteFrame(), "cam0")[lit]),
                               atol=1)


def test_diffuse_interreflection_lights_a_concave_corner_and_nothing_else() -> None:
    matte = GROOVE % {"mirror": 0.0}
    off = _rig(matte)
    on = _rig(matte, "read_noise_dn: 0, shot_noise: false, ambient_dn: 0, interreflection_samples: 8, seed: 1")
    gt = off.ground_truth("cam0")
    faces = gt.lit & (gt.object_id >= 0)
    direct = off.render_clean(WhiteFrame(), "cam0", blur=False)[faces]
    extra = on.render_clean(WhiteFrame(), "cam0", blur=False)[faces] - direct
    ratio = extra / direct
    # the faces (albedo 0.15 and 0.9) light each other: some indirect light everywhere, never more than direct
    assert 0.02 < float(np.median(ratio)) < 0.5 and float(ratio.max()) < 1.0
    # the indirect light on the matte face (albedo 0.9) comes from the dark one (0.15) and vice versa
    right = (gt.object_id[faces] == 1)
    assert float(np.median(ratio[right])) < float(np.median(ratio[~right]))
    # a lone plane has nothing to bounce from
    plane = _rig(PLANE, "read_noise_dn: 0, shot_noise: false, ambient_dn: 0, interreflection_samples: 4, seed: 1")
    alone = _rig(PLANE).render_clean(WhiteFrame(), "cam0")
    np.testing.assert_array_equal(plane.render_clean(WhiteFrame(), "cam0"), alone)


def test_a_translucent_material_blurs_the_pattern_on_its_surface() -> None:
    from appliance.patterns.sequence import PhaseFrame

    clear = _rig(PLANE)
    milky = _rig(PLANE[:-1] + ", material: {subsurface_mm: 1.0}}")
    gt = clear.ground_truth("cam0")
    lit = gt.lit
    period = 16

    def amplitude(rig: VirtualRig) -> np.ndarray:
        s = [rig.render_clean(PhaseFrame(axis="x", period=period, step=k, steps=4), "cam0", blur=False)[lit]
             for k in range(4)]
        return np.hypot(s[0] - s[2], s[1] - s[3]) / 2.0

    # a Gaussian blur of sigma 1 mm on the surface: sigma_px = 1 mm * focal / distance in projector px, and the
    # fringe's amplitude falls by exp(-2 pi^2 sigma_px^2 / P^2) (the 7-tap blur within 10 %)
    dist = np.linalg.norm(gt.xyz[lit] - clear.projector.center, axis=1)
    sigma_px = 1.0 * clear.projector.K[0, 0] / dist
    expected = np.exp(-2 * np.pi**2 * sigma_px**2 / period**2)
    ratio = amplitude(milky) / amplitude(clear)
    np.testing.assert_allclose(np.median(ratio), np.median(expected), rtol=0.1)
    assert 0.3 < float(np.median(ratio)) < 0.8
    # the white level is not changed by the blur
    white = clear.render_clean(WhiteFrame(), "cam0")[lit]
    np.testing.assert_allclose(milky.render_clean(WhiteFrame(), "cam0")[lit], white,
                               rtol=1e-4, atol=1e-3)


def test_the_sim_projector_intensity_and_a_bad_exposure() -> None:
    rig = _rig(PLANE, "read_noise_dn: 0, shot_noise: false, ambient_dn: 20, seed: 1")
    world = SimWorld(rig)
    cam = SimCamera("cam0", SimCameraConfig(), world)
    proj = SimProjector(world)
    out = np.zeros((1, 128, 160), np.uint8)

    async def half_intensity() -> None:
        await cam.open()
        await proj.load(Sequence(1280, 800, (WhiteFrame(),)))
        await proj.set_intensity(0.5)
        await cam.arm(1, out)
        await proj.start()
        await cam.wait_frames(5.0)
        with pytest.raises(ConfigError, match=r"exposure_us = 0\.0"):
            await cam.set_exposure(0.0)
        await cam.close()

    asyncio.run(half_intensity())
    lit = rig.ground_truth("cam0").lit
    white = rig.render_clean(WhiteFrame(), "cam0")[lit].astype(np.float64)
    black = rig.render_clean(BlackFrame(), "cam0")[lit].astype(np.float64)
    np.testing.assert_allclose(out[0][lit].astype(float), np.round(black + 0.5 * (white - black)), atol=1)
