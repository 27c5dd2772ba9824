"""A calibration board on the virtual rig: preset board poses and the board as a scene object.

The board is a plane whose albedo is the printed board image
(:func:`~appliance.calibration.boards.render_board`),
pre-filtered at the reference camera's pixel footprint: the renderer samples the albedo at the pixel
centre's ray, so the pre-filter stands in for the pixel's area integration (no aliased, biased edges).
Preset poses spread the board over the reference camera's image at the working distance (the projector's
``look_at_mm``) with alternating tilts, so that a few poses already constrain focal length and distortion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.calibration.boards import BoardSpec, render_board
from appliance.config.schema import PlaneObject
from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel

F64 = npt.NDArray[np.float64]

BOARD_PX_PER_MM = 10.0
"""Resolution of the board texture (px per mm)."""
INK_ALBEDO = 0.08
PAPER_ALBEDO = 0.85
BACKGROUND_ALBEDO = 0.3
"""Reflectance of the board's black print, its white paper, and the wall behind it (the plane outside)."""
MAX_TILT_DEG = 28.0
"""Tilt of the preset poses about the board's x and y axes (degrees)."""
VISIBLE_MARGIN_PX = 12.0
"""A preset pose keeps every board point this far inside every device's image (px)."""

# (x, y) offset of the board centre in units of the free travel, tilt signs (about x, about y), roll sign
# (about the normal) and depth step (in units of DEPTH_STEP): corners and edges first, mixed tilts
_LAYOUT = (
    (0.0, 0.0, 0, 0, 0, 0), (-1.0, -1.0, 1, -1, 1, 0), (1.0, -1.0, 1, 1, -1, 0), (1.0, 1.0, -1, 1, 1, 0),
    (-1.0, 1.0, -1, -1, -1, 0), (0.0, -1.0, 1, 0, 0, 1), (1.0, 0.0, 0, 1, 1, -1), (0.0, 1.0, -1, 0, 0, 1),
    (-1.0, 0.0, 0, -1, -1, -1), (-1.0, -1.0, -1, 1, 0, -1), (1.0, -1.0, -1, -1, 0, 1),
    (1.0, 1.0, 1, -1, 0, -1),
    (-1.0, 1.0, 1, 1, 0, 1), (0.0, 0.0, 1, 1, 1, -1), (0.0, 0.0, -1, -1, -1, 1), (0.5, -0.5, 1, 0, -1, 0),
    (-0.5, 0.5, 0, 1, 1, 0), (-0.5, -0.5, -1, 0, 1, 0), (0.5, 0.5, 0, -1, -1, 0), (0.0, 0.0, 1, -1, 0, 0),
)  # fmt: skip
MAX_ROLL_DEG = 15.0
"""Rotation of the preset poses about the board normal (degrees)."""
DEPTH_STEP = 0.12
"""Depth change of the preset poses, as a share of the working distance."""


@dataclass(frozen=True)
class BoardPose:
    """Where the board is: ``x_world = R @ x_board + t`` (mm).

    Attributes
    ----------
    R : ndarray, shape (3, 3)
        Board -> world rotation (columns: the board's x, y and normal in the world frame).
    t : ndarray, shape (3,)
        World position of the board origin (mm).
    """

    R: F64
    t: F64

    def world_points(self, board: BoardSpec) -> F64:
        """World coordinates (N, 3) mm of every board point, by id."""
        return np.asarray(board.object_points() @ self.R.T + self.t, np.float64)


def _rot(axis: int, deg: float) -> F64:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _visible(pose: BoardPose, board: BoardSpec, devices: list[CameraModel], margin_px: float) -> bool:
    pts = pose.world_points(board)
    for dev in devices:
        if np.any(dev.to_device(pts)[:, 2] <= 0):
            return False
        px, _ = dev.project(pts)
        u, v = px[:, 0], px[:, 1]
        if not (np.all(u >= margin_px) and np.all(u <= dev.width - 1 - margin_px)
                and np.all(v >= margin_px) and np.all(v <= dev.height - 1 - margin_px)):  # fmt: skip
            return False
    return True


def preset_board_poses(
    board: BoardSpec,
    n: int,
    reference: CameraModel,
    target_mm: F64,
    devices: list[CameraModel] | None = None,
    *,
    max_tilt_deg: float = MAX_TILT_DEG,
) -> list[BoardPose]:
    """``n`` board poses that cover the reference camera's image, each seen whole by every device.

    Parameters
    ----------
    board : BoardSpec
        The board.
    n : int
        Number of poses (the layout repeats with other tilts beyond 20).
    reference : CameraModel
        The reference camera (world frame); the board faces it.
    target_mm : ndarray, shape (3,)
        Centre of the working volume (world, mm), e.g. the projector's ``look_at_mm``.
    devices : list of CameraModel, optional
        Devices that must see the whole board (default: the reference camera only).
    max_tilt_deg : float
        Tilt about the board's axes (degrees).

    Returns
    -------
    list of BoardPose

    Raises
    ------
    CalibrationError
        When the board cannot be placed where every device sees it (too large for the common view).
    """
    devs = devices if devices is not None else [reference]
    centre_board = board.object_points().mean(axis=0)
    target = np.asarray(target_mm, np.float64)
    # board axes facing the reference camera: board x ~ camera x, board y ~ camera y, normal away from it
    base = reference.R.T.copy()
    cam_c = reference.center
    look = target - cam_c
    look /= np.linalg.norm(look)
    base = _facing(base, look)
    right, down = base[:, 0], base[:, 1]
    dist = float(np.linalg.norm(target - cam_c))
    half_w = dist * (reference.width / 2) / reference.K[0, 0]
    half_h = dist * (reference.height / 2) / reference.K[1, 1]
    ext = board.object_points().max(axis=0) - board.object_points().min(axis=0)
    travel = np.array([max(half_w - 0.5 * ext[0], 0.0), max(half_h - 0.5 * ext[1], 0.0)])
    poses: list[BoardPose] = []
    for k in range(n):
        ox, oy, tx, ty, roll, dz = _LAYOUT[k % len(_LAYOUT)]
        tilt = max_tilt_deg * (1.0 if k < len(_LAYOUT) else 0.7)
        R = base @ _rot(0, tx * tilt) @ _rot(1, ty * tilt) @ _rot(2, roll * MAX_ROLL_DEG)
        depth = target + dz * DEPTH_STEP * dist * look
        pose = None
        for shrink in np.linspace(1.0, 0.0, 11):
            c = depth + shrink * (ox * travel[0] * right + oy * travel[1] * down)
            cand = BoardPose(R, c - R @ centre_board)
            if _visible(cand, board, devs, VISIBLE_MARGIN_PX):
                pose = cand
                break
        if pose is None:
            for scale in (0.6, 0.3, 0.0):  # less tilt
                R2 = base @ _rot(0, tx * tilt * scale) @ _rot(1, ty * tilt * scale)
                cand = BoardPose(R2, depth - R2 @ centre_board)
                if _visible(cand, board, devs, VISIBLE_MARGIN_PX):
                    pose = cand
                    break
        if pose is None:
            raise CalibrationError(
                f"virtual rig: the board ({board.describe()}) does not fit into the common view of "
                f"{[d.name for d in devs]} at {dist:.0f} mm; use a smaller board (calibration.board)"
            )
        poses.append(pose)
    return poses


def _facing(base: F64, look: F64) -> F64:
    """Rotate the camera axes ``base`` so that the board normal (column 2) is the viewing direction."""
    z = look
    x = base[:, 0] - (base[:, 0] @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


@dataclass(frozen=True, eq=False)
class BoardTexture:
    """The board image as reflectance, ready to lay on a plane.

    Attributes
    ----------
    image : ndarray, shape (H, W), float64
        Reflectance 0..1, pre-filtered.
    origin_px : ndarray, shape (2,)
        Texture position (px, pixel centres at integers) of the board frame's origin.
    mm_per_px : float
        Texture pixel size (mm).
    """

    image: F64
    origin_px: F64
    mm_per_px: float


def board_texture(board: BoardSpec, footprint_mm: float, px_per_mm: float = BOARD_PX_PER_MM) -> BoardTexture:
    """The board's reflectance image, low-pass filtered at a camera pixel footprint.

    Parameters
    ----------
    board : BoardSpec
        The board.
    footprint_mm : float
        Size of one camera pixel on the board (mm); the texture is blurred with a Gaussian of sigma
        half of it, which stands in for the pixel's area integration.
    px_per_mm : float
        Texture resolution.
    """
    import cv2

    img, origin = render_board(board, px_per_mm)
    refl = INK_ALBEDO + (PAPER_ALBEDO - INK_ALBEDO) * img.astype(np.float64) / 255.0
    sigma = 0.5 * footprint_mm * px_per_mm
    if sigma > 0.3:
        refl = np.asarray(cv2.GaussianBlur(refl, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE), np.float64)
    return BoardTexture(np.ascontiguousarray(refl), np.asarray(origin, np.float64), 1.0 / px_per_mm)


def board_scene(pose: BoardPose, texture: BoardTexture) -> object:
    """A :class:`~appliance.sim.scene.Scene` holding only the board at ``pose`` (a wall of
    ``BACKGROUND_ALBEDO`` around it)."""
    from appliance.sim.scene import PlaneImageAlbedo, Scene

    normal = pose.R[:, 2]
    scene = Scene([PlaneObject(point_mm=tuple(pose.t), normal=tuple(-normal), albedo=BACKGROUND_ALBEDO)])
    origin = pose.t - texture.mm_per_px * (
        texture.origin_px[0] * pose.R[:, 0] + texture.origin_px[1] * pose.R[:, 1]
    )
    scene.set_albedo(
        0,
        PlaneImageAlbedo(
            origin,
            pose.R[:, 0].copy(),
            pose.R[:, 1].copy(),
            texture.image,
            texture.mm_per_px,
            outside=BACKGROUND_ALBEDO,
        ),
    )
    return scene


class VirtualBoard:
    """Moves a board through preset poses on a :class:`~appliance.sim.rig.VirtualRig`.

    Parameters
    ----------
    rig : VirtualRig
        The rig; :meth:`place` replaces its scene.
    board : BoardSpec
        The board.
    n_poses : int
        Number of preset poses.
    """

    def __init__(self, rig: object, board: BoardSpec, n_poses: int) -> None:
        from appliance.sim.rig import VirtualRig

        if not isinstance(rig, VirtualRig):
            raise CalibrationError("VirtualBoard needs a VirtualRig")
        self.rig = rig
        self.board = board
        ref = next(iter(rig.cameras.values()))
        target = np.asarray(rig.cfg.projector.look_at_mm, np.float64)
        devices = [*rig.cameras.values(), rig.projector]
        self.poses = preset_board_poses(board, n_poses, ref, target, devices)
        footprint = float(np.linalg.norm(target - ref.center)) / float(ref.K[0, 0])
        self.texture = board_texture(board, footprint)
        self.index = -1

    def place(self, index: int) -> BoardPose:
        """Put the board at preset pose ``index`` (modulo the number of poses) and return the pose."""
        from appliance.sim.scene import Scene

        self.index = index % len(self.poses)
        pose = self.poses[self.index]
        scene = board_scene(pose, self.texture)
        assert isinstance(scene, Scene)
        self.rig.set_scene(scene)
        return pose

    def next(self) -> BoardPose:
        """Move the board to the next preset pose."""
        return self.place(self.index + 1)

    def advance(self) -> None:
        """Move to the next pose and compute the rig's per-camera geometry for it (blocking, seconds)."""
        self.next()
        self.rig.prepare()
