"""The virtual rig against analytic ground truth: geometry, shadows, photometry, noise, patterns."""

from __future__ import annotations

import math
import struct
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from appliance.config.schema import (
    BoxObject,
    CylinderObject,
    DeviceOptics,
    ImagingConfig,
    MeshObject,
    PlaneObject,
    SphereObject,
    VirtualRigConfig,
)
from appliance.errors import ConfigError, PatternError
from appliance.patterns import (
    BlackFrame,
    GrayFrame,
    OtherFrame,
    PhaseFrame,
    Sequence,
    WhiteFrame,
    gray_phase_sequence,
)
from appliance.patterns.render import frame_profile
from appliance.sim import PlaneImageAlbedo, Scene, VirtualRig, icosphere, load_mesh, projected_light

CAM = DeviceOptics(width=160, height=128, focal_px=250.0, dist=(-0.08, 0.12, 0.0005, -0.0003, 0.0),
                   look_at_mm=(0.0, 0.0, 500.0))
PROJ = DeviceOptics(width=320, height=200, focal_px=380.0, dist=(0.02, -0.01, 0.0, 0.0, 0.0),
                    position_mm=(150.0, 0.0, 0.0), look_at_mm=(0.0, 0.0, 500.0))
QUIET = ImagingConfig(read_noise_dn=0.0, shot_noise=False, camera_blur_px=0.0, ambient_dn=10.0, seed=3)


def _rig(*scene: Any, imaging: ImagingConfig = QUIET, cam: DeviceOptics = CAM, proj: DeviceOptics = PROJ
         ) -> VirtualRig:
    cfg = VirtualRigConfig(cameras={"cam0": cam}, projector=proj, scene=tuple(scene), imaging=imaging)
    return VirtualRig(cfg)


def _pixel_rays(rig: VirtualRig) -> np.ndarray:
    cam = rig.cameras["cam0"]
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    n = cam.undistort_pixels(np.stack([xs.ravel(), ys.ravel()], axis=1))
    return np.concatenate([n, np.ones((n.shape[0], 1))], axis=1)  # camera = world frame


# --- geometry ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("normal", [(0.0, 0.0, -1.0), (0.2, -0.1, -1.0)])
def test_plane_depth_is_exact(normal: tuple[float, float, float]) -> None:
    point = np.array([10.0, -5.0, 520.0])
    rig = _rig(PlaneObject(point_mm=tuple(point), normal=normal))
    gt = rig.ground_truth("cam0")
    assert gt.hit.all()
    rays = _pixel_rays(rig)  # (xn, yn, 1): depth = n.p / n.(xn, yn, 1)
    nv = np.asarray(normal)
    expected = (nv @ point) / (rays @ nv)
    np.testing.assert_allclose(gt.depth.ravel(), expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(gt.xyz.reshape(-1, 3), rays * expected[:, None], rtol=0, atol=1e-9)
    # the points project back onto the pixel centres
    px, _ = rig.cameras["cam0"].project(gt.xyz.reshape(-1, 3))
    ys, xs = np.mgrid[0:CAM.height, 0:CAM.width]
    np.testing.assert_allclose(px, np.stack([xs.ravel(), ys.ravel()], axis=1), atol=1e-6)


def test_sphere_points_lie_on_sphere_and_normals_are_radial() -> None:
    c, r = np.array([5.0, -8.0, 480.0]), 60.0
    rig = _rig(SphereObject(center_mm=tuple(c), radius_mm=r))
    gt = rig.ground_truth("cam0")
    p = gt.xyz[gt.hit]
    assert 0.1 < gt.hit.mean() < 0.9
    assert np.abs(np.linalg.norm(p - c, axis=1) - r).max() < 1e-6
    np.testing.assert_allclose(gt.normal[gt.hit], (p - c) / r, atol=1e-9)
    assert np.isnan(gt.depth[~gt.hit]).all() and (gt.object_id[~gt.hit] == -1).all()


def test_projector_coordinates_reproject() -> None:
    rig = _rig(PlaneObject(point_mm=(0.0, 0.0, 560.0), normal=(0.1, 0.1, -1.0)),
               SphereObject(center_mm=(0.0, 0.0, 500.0), radius_mm=40.0))
    gt = rig.ground_truth("cam0")
    uv, z = rig.projector.project(gt.xyz[gt.hit])
    np.testing.assert_allclose(gt.proj_uv[gt.hit], uv, rtol=0, atol=1e-9)
    assert (z > 0).all()
    lit_uv = gt.proj_uv[gt.lit]
    assert lit_uv.size and lit_uv.min() >= -0.5 and lit_uv[:, 0].max() < PROJ.width - 0.5


def _slab_hit(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray, t_max: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - o) / d, (hi - o) / d
    near = np.minimum(t0, t1).max(axis=1)
    far = np.maximum(t0, t1).min(axis=1)
    return (near <= far) & (far > 0) & (near < t_max)  # type: ignore[no-any-return]


def test_box_in_front_of_plane_casts_a_shadow() -> None:
    box = BoxObject(center_mm=(30.0, 0.0, 470.0), size_mm=(40.0, 40.0, 40.0))
    rig = _rig(PlaneObject(point_mm=(0.0, 0.0, 540.0)), box)
    gt = rig.ground_truth("cam0")
    on_plane = gt.object_id == 0
    shadow = on_plane & ~gt.lit & np.isfinite(gt.proj_uv[..., 0])
    assert shadow.sum() > 100  # a visible shadow ...
    assert (on_plane & gt.lit).sum() > 10 * shadow.sum()  # ... on a mostly lit plane
    # independent check: the segment to the projector crosses the box exactly for the shadowed plane pixels
    p = gt.xyz[on_plane]
    to_p = rig.projector.center - p
    dist = np.linalg.norm(to_p, axis=1)
    lo = np.asarray(box.center_mm) - 20.0
    crossed = _slab_hit(p, to_p / dist[:, None], lo, lo + 40.0, dist)
    uv = gt.proj_uv[on_plane]
    inside = ((uv >= -0.5) & (uv < [PROJ.width - 0.5, PROJ.height - 0.5])).all(axis=1)
    np.testing.assert_array_equal(~gt.lit[on_plane], crossed | ~inside)
    # the box faces facing away from the projector are dark too; the ones facing it are lit
    on_box = gt.object_id == 1
    assert gt.lit[on_box].any() and not gt.lit[on_box].all()


def test_cylinder_and_box_surface_points() -> None:
    cyl = CylinderObject(center_mm=(-30.0, 0.0, 500.0), axis=(0.0, 1.0, 0.2), radius_mm=25.0, height_mm=80.0)
    box = BoxObject(center_mm=(40.0, 10.0, 480.0), size_mm=(30.0, 40.0, 20.0),
                    rotation_deg=(20.0, 30.0, 10.0))
    rig = _rig(cyl, box)
    gt = rig.ground_truth("cam0")
    a = np.asarray(cyl.axis) / np.linalg.norm(cyl.axis)
    q = gt.xyz[gt.object_id == 0] - np.asarray(cyl.center_mm)
    along = q @ a
    radial = np.linalg.norm(q - along[:, None] * a, axis=1)
    on_side = np.abs(radial - cyl.radius_mm) < 1e-6
    on_cap = (np.abs(np.abs(along) - cyl.height_mm / 2) < 1e-6) & (radial <= cyl.radius_mm + 1e-9)
    assert q.shape[0] > 100 and (on_side | on_cap).all() and on_side.any()
    from appliance.sim.scene import rotation_xyz_deg

    local = (gt.xyz[gt.object_id == 1] - np.asarray(box.center_mm)) @ rotation_xyz_deg(box.rotation_deg)
    half = np.asarray(box.size_mm) / 2
    assert local.shape[0] > 100
    assert (np.abs(local) <= half + 1e-6).all()
    assert (np.abs(np.abs(local) - half).min(axis=1) < 1e-6).all()  # on a face


def test_icosphere_mesh_agrees_with_sphere_within_chordal_error() -> None:
    c, r = np.array([0.0, 0.0, 500.0]), 50.0
    v, t = icosphere(c, r, 4)
    tri = v[t]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    # deepest point of a face below the sphere
    sagitta = r - np.abs(np.einsum("ij,ij->i", n, tri[:, 0] - c)).min()
    mesh = MeshObject(vertices_mm=tuple(map(tuple, v)), triangles=tuple(map(tuple, t)))
    sphere = Scene([SphereObject(center_mm=tuple(c), radius_mm=r)])
    tri_scene = Scene([mesh])
    assert tri_scene.n_triangles == 20 * 4**4
    rng = np.random.default_rng(0)
    d = np.column_stack([rng.uniform(-0.1, 0.1, (20000, 2)), np.ones(20000)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hs, hm = sphere.intersect(np.zeros(3), d), tri_scene.intersect(np.zeros(3), d)
    p = d * hs.t[:, None]
    cos_inc = -np.einsum("ij,ij->i", (p - c) / r, d)
    sel = (hs.object_id == 0) & (cos_inc > 0.5)
    assert sel.sum() > 5000
    assert (hm.object_id[sel] == 0).all()
    diff = hm.t[sel] - hs.t[sel]
    assert diff.min() >= -1e-9  # the mesh is inscribed: it is hit at or behind the sphere
    assert (diff <= sagitta / cos_inc[sel] + 1e-9).all()
    assert sagitta < 0.1  # fine mesh: the bound above is tight
    # and the mesh shadows like the sphere (any-hit along the same rays)
    np.testing.assert_array_equal(tri_scene.occluded(np.zeros(3), d[sel], 1e4), np.ones(sel.sum(), bool))


def test_mesh_files_load(tmp_path: Path) -> None:
    v = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]])
    t = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    obj = tmp_path / "tet.obj"
    obj.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in v)
                   + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in t))
    stl = tmp_path / "tet.stl"
    stl.write_bytes(b"\0" * 80 + struct.pack("<I", 4) + b"".join(
        struct.pack("<12fH", 0, 0, 0, *v[tri].ravel(), 0) for tri in t))
    for path in (obj, stl):
        vv, tt = load_mesh(path)
        np.testing.assert_allclose(vv[tt], v[t], atol=1e-6)
    scene = Scene([MeshObject(path=Path("tet.obj"), position_mm=(0.0, 0.0, 100.0))], base_dir=tmp_path)
    hit = scene.intersect(np.array([2.0, 2.0, 0.0]), np.array([[0.0, 0.0, 1.0]]))
    assert hit.object_id[0] == 0 and hit.t[0] == pytest.approx(100.0)
    np.testing.assert_allclose(np.abs(hit.normal[0]), [0.0, 0.0, 1.0], atol=1e-12)
    with pytest.raises(ConfigError, match="suffix"):
        load_mesh(tmp_path / "x.dae")


# --- photometry --------------------------------------------------------------------------------------------


def test_white_frame_lit_bright_shadow_ambient() -> None:
    rig = _rig(PlaneObject(point_mm=(0.0, 0.0, 540.0), albedo=0.7),
               BoxObject(center_mm=(30.0, 0.0, 470.0), size_mm=(40.0, 40.0, 40.0), albedo=0.7),
               imaging=QUIET.model_copy(update={"projector_blur_px": 0.0}))
    gt = rig.ground_truth("cam0")
    img = rig.render_frame(WhiteFrame(), "cam0").astype(np.float64)
    black = rig.render_frame(BlackFrame(), "cam0").astype(np.float64)
    on_plane = gt.object_id == 0
    p = gt.xyz[on_plane & gt.lit]
    to_p = rig.projector.center - p
    cos_inc = -to_p[:, 2] / np.linalg.norm(to_p, axis=1)  # plane normal (0, 0, -1) faces the rig
    expected = 10.0 * 0.7 + 180.0 * 0.7 * cos_inc
    np.testing.assert_allclose(img[on_plane & gt.lit], np.round(expected), atol=1.0)
    shadow = gt.hit & ~gt.lit
    assert shadow.sum() > 100
    np.testing.assert_allclose(img[shadow], 7.0, atol=1.0)  # ambient * albedo only
    np.testing.assert_allclose(black[gt.hit], 7.0, atol=1.0)


def test_noise_matches_read_and_shot_model() -> None:
    im = ImagingConfig(read_noise_dn=2.0, shot_noise=True, electrons_per_dn=4.0, camera_blur_px=0.0,
                       ambient_dn=0.0, projector_blur_px=0.0, seed=11)
    flat = dict(point_mm=(0.0, 0.0, 500.0), albedo=0.5)
    rig = _rig(PlaneObject(**flat), imaging=im)  # type: ignore[arg-type]
    quiet = _rig(PlaneObject(**flat),  # type: ignore[arg-type]
                 imaging=QUIET.model_copy(update={"ambient_dn": 0.0, "projector_blur_px": 0.0}))
    lit = rig.ground_truth("cam0").lit
    clean = quiet.render_frame(WhiteFrame(), "cam0").astype(np.float64)  # rounded mean
    mean = rig.render_clean(WhiteFrame(), "cam0").astype(np.float64)  # exact mean
    stack = rig.render(Sequence(PROJ.width, PROJ.height, (WhiteFrame(),) * 6), "cam0").astype(np.float64)
    resid = (stack - mean)[:, lit]
    expected = np.sqrt(2.0**2 + mean[lit] / 4.0 + 1 / 12)  # read + shot + quantisation
    z = resid / expected
    assert abs(z.std() - 1.0) < 0.15
    assert abs(resid.mean()) < 0.1
    assert np.abs(clean[lit] - mean[lit]).max() <= 0.5 + 1e-6
    # frames of a sequence differ; seeded renders are reproducible, fresh seeds differ
    assert (stack[0] != stack[1]).mean() > 0.5
    a = rig.render(Sequence(PROJ.width, PROJ.height, (WhiteFrame(),)), "cam0", seed=5)
    b = rig.render(Sequence(PROJ.width, PROJ.height, (WhiteFrame(),)), "cam0", seed=5)
    c = rig.render(Sequence(PROJ.width, PROJ.height, (WhiteFrame(),)), "cam0", seed=None)
    np.testing.assert_array_equal(a, b)
    assert (a != c).any()


@pytest.mark.parametrize("bit_depth", [8, 12])
def test_saturation_clips(bit_depth: int) -> None:
    im = QUIET.model_copy(update={"projector_gain_dn": 500.0, "bit_depth": bit_depth})
    rig = _rig(PlaneObject(point_mm=(0.0, 0.0, 500.0)), imaging=im)
    img = rig.render_frame(WhiteFrame(), "cam0")
    full = 2**bit_depth - 1
    assert img.dtype == (np.uint8 if bit_depth == 8 else np.uint16)
    lit = rig.ground_truth("cam0").lit
    assert (img[lit] == full).mean() > 0.99
    dark = rig.render_frame(BlackFrame(), "cam0")
    np.testing.assert_allclose(dark[lit], 0.8 * 10.0 * 2 ** (bit_depth - 8), atol=2 ** (bit_depth - 8))


def _gray_rig(blur: float) -> VirtualRig:
    return _rig(PlaneObject(point_mm=(0.0, 0.0, 520.0), normal=(0.15, 0.1, -1.0)),
                SphereObject(center_mm=(-20.0, 0.0, 470.0), radius_mm=25.0),
                imaging=QUIET.model_copy(update={"projector_blur_px": blur, "ambient_dn": 0.0}))


@pytest.mark.parametrize("frame", [GrayFrame("x", 0), GrayFrame("x", 3, True), GrayFrame("x", 1, False, 8),
                                   GrayFrame("y", 2), GrayFrame("y", 0, True, 4)])
def test_gray_frame_bits_away_from_edges(frame: GrayFrame) -> None:
    sigma = 0.6 if frame.stripe * 2 ** (frame.bit + 1) >= 8 else 0.25  # runs of 2 px: a sharper projector
    rig = _gray_rig(sigma)
    gt = rig.ground_truth("cam0")
    img = rig.render_frame(frame, "cam0").astype(np.float64)
    white = rig.render_frame(WhiteFrame(), "cam0").astype(np.float64)
    c = gt.proj_uv[..., 0 if frame.axis == "x" else 1]
    size = PROJ.width if frame.axis == "x" else PROJ.height
    profile = frame_profile(frame, size)
    ok = gt.lit & (white > 40)
    idx = np.clip(np.floor(np.where(ok, c, 0) + 0.5).astype(int), 0, size - 1)
    # distance to the nearest stripe edge (edges between projector pixels, at k - 0.5)
    changes = np.flatnonzero(np.diff(profile)) + 0.5
    dist = np.abs(c[..., None] - changes).min(axis=-1)
    far = ok & (dist > 3 * sigma + 0.05)
    assert far.sum() > 1000
    expected = profile[idx[far]] * white[far]
    np.testing.assert_allclose(img[far], expected, atol=1.0)


def test_gray_blur_matches_numeric_convolution() -> None:
    sigma = 0.7
    for frame in (GrayFrame("x", 0), GrayFrame("x", 2, True, 3), GrayFrame("x", 5)):
        profile = frame_profile(frame, 200)
        u = np.linspace(20.0, 180.0, 801)
        s = np.linspace(-6 * sigma, 6 * sigma, 12001)
        w = np.exp(-0.5 * (s / sigma) ** 2)
        w /= w.sum()
        pix = np.floor(u[:, None] - s[None, :] + 0.5).astype(int)
        numeric = (profile[pix] * w).sum(axis=1)
        analytic = projected_light(frame, u, np.full(u.size, 100.0), 200, 200, sigma)
        np.testing.assert_allclose(analytic, numeric, atol=1e-3)


def test_phase_frames_encode_projector_coordinate() -> None:
    rig = _gray_rig(0.6)
    gt = rig.ground_truth("cam0")
    period, steps = 16.0, 4
    frames = [PhaseFrame("x", period, s, steps) for s in range(steps)]
    imgs = np.stack([rig.render_clean(f, "cam0", blur=False) for f in frames])
    shifts = 2 * np.pi * np.arange(steps) / steps
    num = -(imgs * np.sin(shifts)[:, None, None]).sum(0)
    den = (imgs * np.cos(shifts)[:, None, None]).sum(0)
    ok = gt.lit
    phase = np.arctan2(num[ok], den[ok])
    truth = 2 * np.pi * gt.proj_uv[..., 0][ok] / period
    err = np.angle(np.exp(1j * (phase - truth)))
    assert np.abs(err).max() < 1e-5
    # modulation: pixel hold (sinc) times the projector blur
    amp = np.hypot(num[ok], den[ok]) * 2 / steps
    white = rig.render_clean(WhiteFrame(), "cam0", blur=False)[ok]
    f = 1 / period
    m = math.sin(math.pi * f) / (math.pi * f) * math.exp(-2 * math.pi**2 * 0.36 * f * f)
    np.testing.assert_allclose(amp / white, m / 2, rtol=1e-4)


def test_gamma_uncorrected_phase_is_distorted() -> None:
    lin = _gray_rig(0.0)
    gam = _rig(PlaneObject(point_mm=(0.0, 0.0, 520.0)),
               imaging=QUIET.model_copy(update={"gamma_corrected": False, "projector_gamma": 2.2,
                                                "ambient_dn": 0.0, "projector_blur_px": 0.0}))
    f = PhaseFrame("x", 16.0, 1, 4)
    a = lin.render_clean(f, "cam0")[lin.ground_truth("cam0").lit]
    w = lin.render_clean(WhiteFrame(), "cam0")[lin.ground_truth("cam0").lit]
    b = gam.render_clean(f, "cam0")[gam.ground_truth("cam0").lit]
    wb = gam.render_clean(WhiteFrame(), "cam0")[gam.ground_truth("cam0").lit]
    assert (a / w).mean() == pytest.approx(0.5, abs=0.02)
    assert (b / wb).mean() < 0.4  # mean of ((1 + cos) / 2) ** 2.2 is about 0.31


def test_board_albedo_hook_and_render_sequence() -> None:
    board = np.indices((8, 10)).sum(axis=0) % 2 * 0.8 + 0.1  # checkerboard, 20 mm squares
    plane = PlaneObject(point_mm=(0.0, 0.0, 500.0))
    scene = Scene([plane])
    image = np.kron(board, np.ones((20, 20)))  # 1 mm pixels
    scene.set_albedo(0, PlaneImageAlbedo(np.array([-95.0, -75.0, 500.0]), np.array([1.0, 0.0, 0.0]),
                                         np.array([0.0, 1.0, 0.0]), image, 1.0, 0.5))
    rig = VirtualRig(VirtualRigConfig(cameras={"cam0": CAM}, projector=PROJ, scene=(plane,), imaging=QUIET),
                     scene=scene)
    img = rig.render_frame(WhiteFrame(), "cam0").astype(np.float64)
    gt = rig.ground_truth("cam0")
    x, y = gt.xyz[..., 0], gt.xyz[..., 1]
    col, row = np.floor((x + 95.0) / 20.0), np.floor((y + 75.0) / 20.0)
    frac_x, frac_y = (x + 95.0) / 20.0 - col, (y + 75.0) / 20.0 - row
    inner = (col >= 0) & (col < 10) & (row >= 0) & (row < 8) & (np.minimum(frac_x, 1 - frac_x) > 0.2) & (
        np.minimum(frac_y, 1 - frac_y) > 0.2)
    light = ((col + row) % 2 == 1) & inner
    dark = ((col + row) % 2 == 0) & inner
    assert light.sum() > 500 and dark.sum() > 500
    assert img[light].min() > 4 * img[dark].max()
    seq = gray_phase_sequence(PROJ.width, PROJ.height)
    stack = rig.render(seq, "cam0")
    assert stack.shape == (len(seq), CAM.height, CAM.width) and stack.dtype == np.uint8
    # another pose of the board: the same rig, a new scene
    rig.set_scene(Scene([PlaneObject(point_mm=(0.0, 0.0, 450.0), normal=(0.3, 0.0, -1.0))]))
    moved = rig.ground_truth("cam0")
    np.testing.assert_allclose(moved.xyz.reshape(-1, 3) @ np.array([0.3, 0.0, -1.0]), -450.0, atol=1e-9)
    with pytest.raises(PatternError, match="projector is"):
        rig.render(gray_phase_sequence(640, 400), "cam0")
    with pytest.raises(ConfigError, match=r"not in virtual_rig\.cameras"):
        rig.ground_truth("nope")


def test_default_rig_sees_a_lit_scene() -> None:
    cfg = VirtualRigConfig()
    small = {"principal_px": None}
    cams = {n: o.model_copy(update={**small, "width": o.width // 8, "height": o.height // 8,
                                    "focal_px": o.focal_px / 8}) for n, o in cfg.cameras.items()}
    rig = VirtualRig(cfg.model_copy(update={"cameras": cams}))
    name = rig.camera_names()[0]
    gt = rig.ground_truth(name)
    assert gt.hit.all()
    assert gt.lit.mean() > 0.9
    assert 500 <= np.nanmin(gt.depth) and np.nanmax(gt.depth) <= 660
    assert len(np.unique(gt.object_id)) == len(cfg.scene)
    baseline = np.linalg.norm(rig.projector.center - rig.cameras[name].center)
    assert 150 <= baseline <= 200


def test_two_cameras_render_concurrently_and_reproducibly() -> None:
    cam1 = CAM.model_copy(update={"position_mm": (-60.0, 0.0, 0.0), "look_at_mm": (0.0, 0.0, 500.0)})
    cfg = VirtualRigConfig(cameras={"cam0": CAM, "cam1": cam1}, projector=PROJ,
                           scene=(PlaneObject(point_mm=(0.0, 0.0, 520.0), texture=0.3),
                                  SphereObject(center_mm=(0.0, 0.0, 480.0), radius_mm=30.0)),
                           imaging=ImagingConfig(seed=4))
    seq = gray_phase_sequence(PROJ.width, PROJ.height)
    serial = VirtualRig(cfg)
    expected = {n: serial.render(seq, n) for n in serial.camera_names()}
    assert (expected["cam0"] != expected["cam1"]).any()
    rig = VirtualRig(cfg)
    with ThreadPoolExecutor(2) as pool:
        got = dict(zip(rig.camera_names(), pool.map(lambda n: rig.render(seq, n), rig.camera_names()),
                       strict=True))
    for n in rig.camera_names():
        np.testing.assert_array_equal(got[n], expected[n])
    # both cameras see the sphere's front at the same world points: ground truth is in one world frame
    gt0, gt1 = rig.ground_truth("cam0"), rig.ground_truth("cam1")
    for gt in (gt0, gt1):
        on = gt.object_id == 1
        assert np.abs(np.linalg.norm(gt.xyz[on] - [0.0, 0.0, 480.0], axis=1) - 30.0).max() < 1e-6


def test_unknown_frame_kind_is_refused() -> None:
    rig = _rig(PlaneObject(point_mm=(0.0, 0.0, 500.0)))
    with pytest.raises(PatternError, match="not known"):
        rig.render_frame(OtherFrame("dots"), "cam0")
    light = projected_light(WhiteFrame(), np.array([-3.0, 0.0, 10.0, 319.4, 330.0]), np.full(5, 100.0),
                            PROJ.width, PROJ.height, 0.5)
    np.testing.assert_allclose(light, [0.0, 0.8413, 1.0, 0.5793, 0.0], atol=2e-4)  # Phi(1), Phi(0.2)


def test_lean_rig_renders_the_same_and_computes_truth_on_request() -> None:
    """The service's rig (keep_truth=False) casts the same geometry in 64-row chunks as the full rig: identical
    frames (noise included) and identical ground truth, which it computes only when asked for."""
    from appliance.config.schema import PlaneObject, SphereObject

    cam = DeviceOptics(width=160, height=150, focal_px=250.0, dist=(-0.08, 0.12, 0.0005, -0.0003, 0.0),
                       look_at_mm=(0.0, 0.0, 500.0))  # 150 rows: two full chunks and a short one
    scene = (PlaneObject(point_mm=(0, 0, 600), normal=(0, 0.1, -1), texture=0.3),
             SphereObject(center_mm=(-20, 10, 520), radius_mm=40))
    cfg = VirtualRigConfig(cameras={"cam0": cam}, projector=PROJ, scene=scene, imaging=ImagingConfig(seed=5))
    full, lean = VirtualRig(cfg), VirtualRig(cfg, keep_truth=False)
    seq = gray_phase_sequence(PROJ.width, PROJ.height, periods=(16,), steps=4)
    np.testing.assert_array_equal(full.render(seq, "cam0"), lean.render(seq, "cam0"))
    assert not lean._truth and not lean._rays  # rendering kept neither
    a, b = full.ground_truth("cam0"), lean.ground_truth("cam0")
    for name in ("xyz", "depth", "hit", "lit", "proj_uv", "normal", "object_id"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert np.isfinite(a.depth).mean() > 0.9 and a.lit.mean() > 0.5


@pytest.mark.parametrize("sigma", [0.3, 0.5, 1.0, 2.5])
def test_camera_blur_matches_opencv_gaussian(sigma: float) -> None:
    """The renderer's own blur (no OpenCV in the service) against ``cv2.GaussianBlur`` with replicated borders:
    the same to 1e-3 DN for one pass (sigma <= 1.1 px); a wider one is several passes whose variances add, the
    same inside; only near the replicated border do they differ (by less than a fifth of the range)."""
    import cv2

    from appliance.sim import _sim_kernels as k

    img = (np.random.default_rng(7).random((203, 301)) * 255).astype(np.float32)
    ref = cv2.GaussianBlur(img, (0, 0), sigma, sigmaY=sigma, borderType=cv2.BORDER_REPLICATE)
    passes, w = k.gaussian_passes(sigma)
    assert w.shape == (2 * k.BLUR_RADIUS + 1,) and abs(float(w.sum()) - 1.0) < 1e-6
    out = img.copy()
    scratch = k.blur_scratch(*img.shape)
    for _ in range(passes):
        k.gaussian_blur_inplace(out, w, scratch)
    diff = np.abs(out - ref)
    inner = diff[12:-12, 12:-12]
    if passes == 1:
        assert diff.max() < 1e-3, diff.max()
    else:
        assert passes > 1 and inner.max() < 0.02, inner.max()
        assert diff.max() < 0.2 * 255, diff.max()  # only the replicated border differs


def test_renderer_keeps_only_the_coded_axes_and_rebuilds_for_another() -> None:
    """A rig told that only columns are coded keeps no row coordinates (5 MB a 1280x1024 camera); a row frame
    rebuilds that camera's renderer with both axes and renders exactly what a rig with both renders."""
    both = _rig(PlaneObject(point_mm=(0.0, 0.0, 520.0), normal=(0.1, 0.2, -1.0)))
    lean = _rig(PlaneObject(point_mm=(0.0, 0.0, 520.0), normal=(0.1, 0.2, -1.0)))
    lean.coded_axes = frozenset({"x"})
    cols, rows = GrayFrame("x", 2), GrayFrame("y", 1)
    np.testing.assert_array_equal(lean.render_clean(cols, "cam0"), both.render_clean(cols, "cam0"))
    assert lean._renderers["cam0"].axes == {"x"} and set(lean._renderers["cam0"]._coord) == {"x"}
    np.testing.assert_array_equal(lean.render_clean(WhiteFrame(), "cam0"), both.render_clean(WhiteFrame(), "cam0"))
    np.testing.assert_array_equal(lean.render_clean(rows, "cam0"), both.render_clean(rows, "cam0"))
    assert lean._renderers["cam0"].axes == {"x", "y"}
