"""The projector visibility check on depth maps made by hand (exact geometry, no decoder): a point with a surface
nearer the projector on its projector ray is dropped with reason HIDDEN, the counts follow, the decoder's
evidence of a surface (pixels lit by two copies of the pattern) hides what lies behind it, and a surface seen at a
steep angle from the projector loses nothing."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from appliance.geometry.camera import CameraModel, look_at
from appliance.reconstruct.decode import reason_advice
from appliance.reconstruct.triangulate import ProjectorTriangulator
from appliance.reconstruct.types import DecodedMaps, Reason
from appliance.reconstruct.visibility import ProjectorVisibility

H, W = 240, 320


def _devices() -> tuple[CameraModel, CameraModel]:
    cam = CameraModel("cam0", np.array([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]]), np.zeros(5), W, H)
    r, t = look_at(np.array([160.0, 0, 0]), np.array([0.0, 0, 600]))
    proj = CameraModel("projector", np.array([[700.0, 0, 319.5], [0, 700.0, 199.5], [0, 0, 1]]),
                       np.array([0.02, -0.01, 0, 0, 0]), 640, 400, r, t)  # fmt: skip
    return cam, proj


def _rays(cam: CameraModel) -> npt.NDArray[np.float64]:
    """Normalised (x/z, y/z) of every pixel (H, W, 2): the camera has no distortion."""
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    return np.stack([(cols - cam.K[0, 2]) / cam.K[0, 0], (rows - cam.K[1, 2]) / cam.K[1, 1]], axis=-1)


def _plane_depth(cam: CameraModel, point: npt.ArrayLike, normal: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Camera-frame depth of a plane at every pixel (the camera is the world frame)."""
    n, p = np.asarray(normal, float), np.asarray(point, float)
    m = _rays(cam)
    den = m[..., 0] * n[0] + m[..., 1] * n[1] + n[2]
    return np.asarray(p @ n / den, np.float32)


class _Scan:
    def __init__(self, depth: npt.NDArray[np.float32]) -> None:
        self.cam, self.proj = _devices()
        self.tri = ProjectorTriangulator(self.cam, self.proj, "x")
        self.vis = ProjectorVisibility(self.proj, {"cam0": self.tri})
        self.depth = np.array(depth, np.float32)  # a copy: the check writes into it
        self.sigma = np.where(np.isfinite(depth), 0.05, np.nan).astype(np.float32)
        kept = np.isfinite(self.depth)
        self.counts = np.concatenate([[0], kept.sum(axis=1)]).astype(np.int64)
        self.stats = np.zeros((H, 6), np.int64)
        self.stats[:, 5] = kept.sum(axis=1)
        self.reason = np.where(kept, Reason.DECODED, Reason.SHADOW).astype(np.uint8)

    def run(self, evidence: npt.NDArray[np.float32] | None = None) -> npt.NDArray[np.bool_]:
        before = np.isfinite(self.depth)
        n = self.vis.apply({"cam0": self.depth}, {"cam0": self.sigma}, {"cam0": self.counts}, {"cam0": self.stats},
                           {"cam0": self.reason}, {"cam0": evidence})["cam0"]  # fmt: skip
        dropped = before & ~np.isfinite(self.depth)
        assert n == dropped.sum()
        assert np.array_equal(self.reason == Reason.HIDDEN, dropped)
        assert np.isnan(self.sigma[dropped]).all()
        kept = np.isfinite(self.depth)
        assert np.array_equal(self.counts[1:], kept.sum(axis=1)) and np.array_equal(self.stats[:, 5], kept.sum(axis=1))
        return dropped

    def codes(self, region: npt.NDArray[np.bool_], depth: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """The decoder's evidence for the pixels of ``region`` seeing ``depth``: row, col and their true u."""
        rows, cols = np.nonzero(region)
        m = _rays(self.cam)[rows, cols]
        z = depth[rows, cols].astype(float)
        px, _ = self.proj.project(np.stack([m[:, 0] * z, m[:, 1] * z, z], axis=1))
        return np.stack([rows, cols, px[:, 0], np.full(len(rows), np.nan)], axis=1).astype(np.float32)


Mask = npt.NDArray[np.bool_]


def _wall_on_projector_ray(cam: CameraModel, proj: CameraModel, depth: npt.NDArray[np.float32], wall: Mask,
                           z_wall: float) -> tuple[Mask, Mask]:
    """Exact truth for points behind the fronto-parallel wall z = z_wall: per pixel, whether the projector's ray to
    its point crosses the wall where the camera sees wall in all of the 5 x 5 pixels around (hidden: surely
    dropped), or in none of them (surely kept)."""
    m = _rays(cam)
    pts = np.stack([m[..., 0] * depth, m[..., 1] * depth, depth], axis=-1)
    c = proj.center
    with np.errstate(invalid="ignore"):
        s = (z_wall - c[2]) / (pts[..., 2] - c[2])
    x, y = c[0] + s * (pts[..., 0] - c[0]), c[1] + s * (pts[..., 1] - c[1])
    col = np.rint(x / z_wall * cam.K[0, 0] + cam.K[0, 2])
    row = np.rint(y / z_wall * cam.K[1, 1] + cam.K[1, 2])
    ok = np.isfinite(col) & np.isfinite(row)
    col, row = np.where(ok, col, -99).astype(int), np.where(ok, row, -99).astype(int)
    seen = np.zeros((H + 4, W + 4), float)
    seen[2:-2, 2:-2] = wall
    n = np.zeros((H, W))
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            rr, cc = np.clip(row + dy + 2, 0, H + 3), np.clip(col + dx + 2, 0, W + 3)
            n += seen[rr, cc]
    return ok & (n == 25), ~ok | (n == 0)


def test_a_ghost_behind_a_lit_wall_is_dropped_where_the_wall_is_seen_and_the_wall_kept() -> None:
    cam, proj = _devices()
    wall = _plane_depth(cam, [0, 0, 600], [0, 0, -1])
    depth = wall.copy()
    ghost = np.zeros((H, W), bool)
    ghost[100:140, 140:200] = True
    depth[ghost] = 680.0  # seen "through" a mirror: behind the wall the projector lights
    scan = _Scan(depth)
    dropped = scan.run()
    hidden, free = _wall_on_projector_ray(cam, proj, depth, ~ghost, 600.0)
    assert (ghost & hidden).sum() > 300 and (ghost & free).sum() > 1000  # the wall hides part of the ghost only
    assert dropped[ghost & hidden].all()
    assert not dropped[ghost & free].any()
    assert not dropped[~ghost].any()


def test_a_part_in_front_casts_a_projector_shadow_its_points_behind_are_dropped() -> None:
    # a box face 150 mm in front of the wall: the wall points on its projector rays cannot be lit directly
    cam, proj = _devices()
    wall = _plane_depth(cam, [0, 0, 600], [0, 0, -1])
    depth = wall.copy()
    part = np.zeros((H, W), bool)
    part[90:150, 130:190] = True
    depth[part] = 450.0
    scan = _Scan(depth)
    dropped = scan.run()
    assert not dropped[part].any()
    # where the projector's ray to each wall point crosses z = 450: inside the part's face means in its shadow
    m = _rays(cam)
    pts = np.stack([m[..., 0] * 600.0, m[..., 1] * 600.0, np.full((H, W), 600.0)], axis=-1)
    c = proj.center
    s = (450.0 - c[2]) / (pts[..., 2] - c[2])
    x = c[0] + s * (pts[..., 0] - c[0])
    y = c[1] + s * (pts[..., 1] - c[1])
    xs, ys = m[part][:, 0] * 450.0, m[part][:, 1] * 450.0
    inside = (x > xs.min() + 2) & (x < xs.max() - 2) & (y > ys.min() + 2) & (y < ys.max() - 2) & ~part
    outside = ~((x > xs.min() - 3) & (x < xs.max() + 3) & (y > ys.min() - 3) & (y < ys.max() + 3)) & ~part
    assert inside.sum() > 500 and dropped[inside].mean() == 1.0, dropped[inside].mean()
    assert not dropped[outside].any()


def test_the_decoders_evidence_of_a_surface_hides_what_lies_behind_it() -> None:
    # the wall's pixels in front of the ghost gave no point (two copies of the pattern): their codes still say
    # that the projector lights a surface there
    cam, proj = _devices()
    wall = _plane_depth(cam, [0, 0, 600], [0, 0, -1])
    ghost = np.zeros((H, W), bool)
    ghost[100:140, 90:100] = True  # its projector rays cross the wall at columns 102-116
    blended = np.zeros((H, W), bool)
    blended[60:180, 100:] = True  # the wall the ghost's projector rays cross (the projector is to the right)
    depth = wall.copy()
    depth[ghost] = 680.0
    depth[blended] = np.nan
    alone = _Scan(depth.copy())
    dropped = alone.run()
    hidden, _ = _wall_on_projector_ray(cam, proj, depth, ~ghost & ~blended, 600.0)
    assert dropped[ghost].sum() < 0.2 * ghost.sum() and dropped[ghost & hidden].all()
    scan = _Scan(depth.copy())
    dropped = scan.run(scan.codes(blended, wall))
    hidden, _ = _wall_on_projector_ray(cam, proj, depth, ~ghost, 600.0)
    assert (ghost & hidden).sum() > 0.8 * ghost.sum()
    assert dropped[ghost & hidden].all()
    assert not dropped[~ghost].any()


@pytest.mark.parametrize("grazing_deg", [13.0, 20.0, 45.0])
def test_a_surface_steep_to_the_projector_loses_nothing(grazing_deg: float) -> None:
    # a plane through (0, 0, 600) turned about the vertical; kept where the projector's rays meet it at
    # grazing_deg or more (the check allows down to 10 degrees): one cell spreads over centimetres of depth there
    cam, proj = _devices()
    axis = proj.R[2]  # the projector's optical axis (world)
    up = np.array([0.0, 1.0, 0.0])
    a = np.radians(grazing_deg)
    normal = np.cross(np.cos(a) * axis + np.sin(a) * np.cross(axis, up), up)
    depth = _plane_depth(cam, [0, 0, 600], normal)
    m = _rays(cam)
    ray = np.stack([m[..., 0] * depth, m[..., 1] * depth, depth], axis=-1) - proj.center
    with np.errstate(invalid="ignore"):
        angle = np.degrees(np.arcsin(np.abs(ray @ normal) / np.linalg.norm(ray, axis=-1) / np.linalg.norm(normal)))
    depth[~((depth > 300) & (depth < 1200) & (angle >= grazing_deg))] = np.nan
    assert np.isfinite(depth).sum() > 0.1 * H * W
    scan = _Scan(depth)
    assert not scan.run().any()


def test_when_hidden_points_dominate_one_plain_line_says_what_to_do() -> None:
    reason = np.zeros((H, W), np.uint8)
    reason[: H // 3] = Reason.HIDDEN
    reason[-10:] = Reason.SHADOW  # not lit: not counted
    maps = DecodedMaps(np.zeros((H, W), np.float32), np.zeros((H, W), np.float32), reason == 0,
                       np.zeros((H, W), np.float32), reason=reason)  # fmt: skip
    line = reason_advice(maps, "cam0")
    assert line is not None and line.startswith("cam0: 35 % of the lit pixels are hidden from the projector"), line
    assert "reflection" in line and "tilt the part" in line
    reason[: H // 3] = Reason.DECODED
    reason[:10] = Reason.HIDDEN  # 4 %: no line
    assert reason_advice(maps, "cam0") is None
