"""Model selection by held-out error and the weakness report, on exactly projected board views with noise."""

from __future__ import annotations

import numpy as np

from appliance.calibration.advice import assess, missing_regions, next_pose_hint
from appliance.calibration.boards import BoardSpec, Detection
from appliance.calibration.bundle import Observation, bundle_adjust
from appliance.calibration.intrinsics import calibrate_camera
from appliance.calibration.selection import select_model
from appliance.calibration.virtual import BoardPose, preset_board_poses
from appliance.geometry.camera import CameraModel

BOARD = BoardSpec(type="chessboard", cols=9, rows=7, square_mm=20)
K = np.array([[1500.0, 0.0, 645.0], [0.0, 1500.0, 508.0], [0.0, 0.0, 1.0]])


def camera(dist: tuple[float, ...]) -> CameraModel:
    return CameraModel("cam0", K, np.array(dist), 1280, 1024)


def views(cam: CameraModel, poses: list[BoardPose], noise_px: float, seed: int = 0) -> list[Detection | None]:
    rng = np.random.default_rng(seed)
    ids = np.arange(BOARD.n_points, dtype=np.int32)
    out: list[Detection | None] = []
    for p in poses:
        px = cam.project(p.world_points(BOARD))[0] + rng.normal(0, noise_px, (BOARD.n_points, 2))
        out.append(Detection(ids, px, BOARD.object_points(), cam.size))
    return out


def rich_poses(cam: CameraModel, n: int = 12) -> list[BoardPose]:
    return preset_board_poses(BOARD, n, cam, np.array([0.0, 0.0, 500.0]))


def centred_poses(cam: CameraModel, n: int) -> list[BoardPose]:
    """The board always in the middle, facing the camera, at one distance, barely tilted."""
    poses = []
    centre = BOARD.object_points().mean(axis=0)
    for k in range(n):
        a = np.deg2rad(3.0 * (-1) ** k)
        R = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
        poses.append(BoardPose(R, np.array([2.0 * k, 0.0, 900.0]) - R @ centre))
    return poses


def test_selection_refuses_k3_the_views_cannot_determine() -> None:
    cam = camera((-0.1, 0.05, 0.0, 0.0, 0.0))
    dets = views(cam, rich_poses(cam, 8), 0.1, seed=1)
    res, choice = select_model(dets, cam.size)
    seen: set[str] = set()
    for c in choice.candidates:  # the rule: an added coefficient is freed only when its std is below its value
        names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
        values = dict(zip(names, c.result.camera.dist, strict=False))
        added = {"k3p": ("k3",), "rational": ("k3", "k4", "k5", "k6")}.get(c.model, ())
        own = {p for p in added if c.result.std_devs[p] >= abs(values[p])}
        assert set(c.undetermined) == own | (seen & set(added))  # and never once a simpler model failed it
        seen |= set(c.undetermined)
    k3p = next(c for c in choice.candidates if c.model == "k3p")
    # the true k3 is 0: its estimate from 8 views is noise, smaller than its standard deviation
    assert "k3" in k3p.undetermined and not k3p.admissible
    assert choice.chosen == "k2p" and res.camera.dist[4] == 0.0
    assert "k3p refused: the views do not determine it" in choice.reason
    # refused candidates are not fitted view by view; the admitted ones are
    assert all((c.held_out.rms_px > 0) == c.admissible for c in choice.candidates)
    # the held-out error is what a new view sees: above the fitted RMS, about the noise (0.1 px * sqrt 2)
    best = choice.best
    assert best.rms_px < best.held_out.rms_px < 0.2


def test_selection_takes_k3_when_the_lens_needs_it() -> None:
    cam = camera((-0.25, 0.1, 0.0, 0.0, 0.4))
    dets = views(cam, rich_poses(cam, 12), 0.05)
    res, choice = select_model(dets, cam.size)
    assert choice.chosen in ("k3p", "rational")
    k2p = next(c for c in choice.candidates if c.model == "k2p")
    assert choice.best.held_out.rms_px < 0.99 * k2p.held_out.rms_px
    assert "predicts left-out views best" in choice.reason
    np.testing.assert_allclose(res.camera.K[0, 0], 1500.0, rtol=1e-3)


def test_forced_model_is_scored_but_not_replaced() -> None:
    cam = camera((-0.1, 0.05, 0.0, 0.0, 0.0))
    _, choice = select_model(views(cam, rich_poses(cam, 6), 0.1), cam.size, forced="rational")
    assert choice.forced and choice.chosen == "rational" and len(choice.candidates) == 1
    assert "(forced)" in choice.lines()[0]


def test_weak_calibration_says_what_to_add() -> None:
    cam = camera((-0.1, 0.05, 0.0, 0.0, 0.0))
    dets = views(cam, centred_poses(cam, 5), 0.1)
    res, choice = select_model(dets, cam.size, candidates=("k2p",))
    kinds = {w.kind: w for w in assess(res, choice)}
    assert {"few_views", "image_coverage", "depth_range", "tilt", "board_small"} <= set(kinds)
    assert "board in the top-left of the image" in kinds["image_coverage"].poses
    assert any("nearer" in p for p in kinds["depth_range"].poses)
    assert any("tilted" in p for p in kinds["tilt"].poses)
    assert kinds["few_views"].message.startswith("only 5 views")
    assert len(kinds["few_views"].poses) == 5


def test_good_calibration_has_no_coverage_weakness() -> None:
    cam = camera((-0.1, 0.05, 0.0, 0.0, 0.0))
    poses = rich_poses(cam, 12)
    res, choice = select_model(views(cam, poses, 0.1), cam.size, candidates=("k2p",))
    kinds = {w.kind for w in assess(res, choice)}
    assert not kinds & {"few_views", "image_coverage", "tilt", "board_small", "dominant_view"}


def test_one_view_dominating_is_named() -> None:
    """A board bent by ~1 px in one view: leaving single views out moves the intrinsics by several std."""
    cam = camera((-0.1, 0.05, 0.0, 0.0, 0.0))

    def weaknesses(bend_px: float) -> list[str]:
        dets = views(cam, rich_poses(cam, 6), 0.05, seed=2)
        d = dets[3]
        assert d is not None
        q = d.image_points.copy()
        q[:, 0] += bend_px * ((d.object_points[:, 0] - d.object_points[:, 0].mean()) / 80.0) ** 2
        dets[3] = Detection(d.ids, q, d.object_points, d.image_size)
        res, choice = select_model(dets, cam.size, candidates=("k2p",))
        return [w.message for w in assess(res, choice) if w.kind == "dominant_view"]

    assert weaknesses(0.0) == []
    bent = weaknesses(1.0)
    assert any(m.startswith("view #3 decides") for m in bent), bent
    assert all("std)" in m and "without it" in m for m in bent)


def test_live_hints_name_the_emptiest_region() -> None:
    cam = camera((0.0, 0.0, 0.0, 0.0, 0.0))
    pts = [d.image_points for d in views(cam, centred_poses(cam, 2), 0.0) if d is not None]
    missing = missing_regions(pts, cam.size)
    assert "centre" not in missing and len(missing) == 8
    hint = next_pose_hint(pts, cam.size, "cam0")
    assert hint is not None and hint.startswith(f"next pose: put the board into the {missing[0]} of cam0's image")
    everything = [np.array([[0.0, 0.0], [1279.0, 0.0], [1279.0, 1023.0], [0.0, 1023.0]])]
    assert next_pose_hint(everything, cam.size, "cam0") is None


def test_bundle_holds_fixed_intrinsics_and_reports_correlations() -> None:
    cam = camera((-0.1, 0.05, 0.0, 0.0, 0.0))
    poses = rich_poses(cam, 6)
    dets = views(cam, poses, 0.05)
    start = calibrate_camera(dets, cam.size, "k2p")
    obs = [Observation("cam0", k, d.object_points, d.image_points) for k, d in enumerate(dets) if d is not None]
    init = {k: (start.rvecs[k], start.tvecs[k]) for k in range(len(dets))}
    K_off = K.copy()
    K_off[0, 0] += 3.0
    held = CameraModel("cam0", K_off, start.camera.dist, 1280, 1024)
    fixed = bundle_adjust({"cam0": held}, {"cam0": "k2p"}, obs, init, fixed={"cam0"})
    np.testing.assert_array_equal(fixed.devices["cam0"].K, K_off)
    assert fixed.fixed == ("cam0",) and fixed.std_devs["cam0"] == {}
    free = bundle_adjust({"cam0": held}, {"cam0": "k2p"}, obs, init)
    # freed, it returns to the least-squares optimum OpenCV found from the same points
    np.testing.assert_allclose(free.devices["cam0"].K, start.camera.K, atol=0.02)
    partner, rho = free.correlations["cam0"]["fx"]
    assert partner == "fy" and rho > 0.5  # fx and fy move together with the board distance
