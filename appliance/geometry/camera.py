"""Pinhole camera (and projector) model with OpenCV distortion.

Conventions: pixel centres at integer coordinates, ``x_device = R @ x_world + T`` in millimetres, the
world frame is the first (reference) camera's frame. Distortion coefficients are in OpenCV order
``k1 k2 p1 p2 [k3 [k4 k5 k6]]``. A projector is modelled as an inverse camera with the same class.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from appliance.errors import CalibrationError

F64 = npt.NDArray[np.float64]
UNDISTORT_ITERATIONS = 30
"""Newton steps at most; from the distorted point as the first guess, ordinary lenses settle in 3-6."""


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Intrinsics, distortion and pose of one camera or projector.

    Attributes
    ----------
    name : str
        Device name, as in the configuration (``cam0``, ``projector``).
    K : ndarray, shape (3, 3)
        Camera matrix (pixels).
    dist : ndarray, shape (N,)
        Distortion coefficients, OpenCV order (N in 0, 4, 5, 8).
    width, height : int
        Image size (pixels).
    R : ndarray, shape (3, 3)
        Rotation world -> device.
    T : ndarray, shape (3,)
        Translation world -> device (mm).
    rms : float
        Reprojection RMS of the calibration that produced it (px); NaN when unknown.
    """

    name: str
    K: F64
    dist: F64
    width: int
    height: int
    R: F64 = field(default_factory=lambda: np.eye(3))
    T: F64 = field(default_factory=lambda: np.zeros(3))
    rms: float = float("nan")

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        dist = np.asarray(self.dist, dtype=np.float64).ravel()
        R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        T = np.asarray(self.T, dtype=np.float64).ravel()
        if dist.size not in (0, 4, 5, 8, 12, 14):
            raise CalibrationError(
                f"{self.name}: dist has {dist.size} coefficients: must be 0, 4, 5, 8, 12 or 14 (OpenCV order)"
            )
        if T.size != 3:
            raise CalibrationError(f"{self.name}: T has {T.size} values: must be 3 (mm)")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise CalibrationError(f"{self.name}: K focal lengths {K[0, 0]}, {K[1, 1]}: must be > 0 px")
        if abs(np.linalg.det(R) - 1.0) > 1e-6:
            raise CalibrationError(f"{self.name}: R is not a rotation (det = {np.linalg.det(R):.6f})")
        if self.width < 1 or self.height < 1:
            raise CalibrationError(f"{self.name}: size {self.width}x{self.height}: must be positive")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "T", T)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (self.width, self.height)

    @property
    def center(self) -> F64:
        """Optical centre in world coordinates (mm), shape (3,)."""
        return -self.R.T @ self.T

    def dist_padded(self, n: int = 8) -> F64:
        """Distortion padded with zeros to ``n`` coefficients (OpenCV order)."""
        out = np.zeros(max(n, self.dist.size))
        out[: self.dist.size] = self.dist
        return out

    def to_device(self, xyz_world: F64) -> F64:
        """World points (N, 3) mm -> device-frame points (N, 3) mm."""
        return np.asarray(xyz_world, dtype=np.float64) @ self.R.T + self.T

    def distort_normalized(self, xn: F64, yn: F64) -> tuple[F64, F64]:
        """Apply the distortion model to normalised image coordinates (any equal shapes)."""
        d = self.dist_padded(8)
        k1, k2, p1, p2, k3, k4, k5, k6 = d[:8]
        r2 = xn * xn + yn * yn
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        return xd, yd

    def project(self, xyz_world: F64) -> tuple[F64, F64]:
        """Project world points to distorted pixel coordinates.

        Parameters
        ----------
        xyz_world : ndarray, shape (N, 3)
            Points in the world frame (mm).

        Returns
        -------
        px : ndarray, shape (N, 2)
            Pixel coordinates (x = column, y = row), NaN behind the device.
        z : ndarray, shape (N,)
            Depth along the optical axis in the device frame (mm).
        """
        if self.dist.size > 8:
            raise CalibrationError(f"{self.name}: thin-prism/tilt distortion is not supported by project()")
        p = self.to_device(np.asarray(xyz_world, dtype=np.float64).reshape(-1, 3))
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = np.where(z > 0, p[:, 0] / z, np.nan)
            yn = np.where(z > 0, p[:, 1] / z, np.nan)
        xd, yd = self.distort_normalized(xn, yn)
        K = self.K
        px = np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)
        return px, z

    def undistort_pixels(self, px: F64) -> F64:
        """Distorted pixels (N, 2) -> normalised undistorted image coordinates (N, 2).

        The distortion model is inverted to 1e-12 (normalised units) by Newton's method on its exact Jacobian
        (``_distortion_kernels.undistort_points``, the Jacobian the triangulation uses) for up to 12
        coefficients, without OpenCV (the service never loads it); with the tilt terms (14 coefficients) by
        OpenCV's ``undistortPointsIter``. A pixel whose inversion does not converge, or lands past a fold of
        the model (outside the region where it is invertible), is NaN.
        """
        pts = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        K = self.K
        yd = (pts[:, 1] - K[1, 2]) / K[1, 1]
        xd = (pts[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        if self.dist.size == 0 or not np.any(self.dist):
            return np.stack([xd, yd], axis=1)
        if self.dist.size > 12:
            return self._undistort_opencv(xd, yd)
        from appliance.geometry._distortion_kernels import undistort_points

        out = np.empty((pts.shape[0], 2))
        undistort_points(xd, yd, self.dist_padded(12), UNDISTORT_ITERATIONS, out)
        return out

    def _undistort_opencv(self, xd: F64, yd: F64) -> F64:
        """Tilted-sensor models: OpenCV's iterative inversion (to 1e-12, 100 iterations at most)."""
        import cv2

        pts = np.ascontiguousarray(np.stack([xd, yd], axis=1).reshape(-1, 1, 2))
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        eye = np.eye(3)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
            und = cv2.undistortPointsIter(pts, eye, self.dist, None, None, crit)
        else:  # OpenCV 5 folded the criteria into undistortPoints
            und = cv2.undistortPoints(pts, eye, self.dist, R=None, P=None, criteria=crit)
        return und.reshape(-1, 2).astype(np.float64)  # type: ignore[no-any-return]

    def pixel_rays_device(self, row0: int = 0, row1: int | None = None) -> F64:
        """Unit ray directions of every pixel of rows ``row0:row1`` (default all) in the device frame.

        Returns
        -------
        ndarray, shape (row1 - row0, width, 3), float64
        """
        row1 = self.height if row1 is None else row1
        ys, xs = np.mgrid[row0:row1, 0 : self.width].astype(np.float64)
        n = self.undistort_pixels(np.stack([xs.ravel(), ys.ravel()], axis=1))
        d = np.concatenate([n, np.ones((n.shape[0], 1))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d.reshape(row1 - row0, self.width, 3)

    def with_pose(self, R: F64, T: F64) -> CameraModel:
        """A copy with another pose."""
        return CameraModel(self.name, self.K, self.dist, self.width, self.height, R, T, self.rms)


ProjectorModel = CameraModel
"""A projector is an inverse camera: the same model, ``width``/``height`` are the projector's."""


def look_at(eye_mm: F64, target_mm: F64, up: F64 | None = None) -> tuple[F64, F64]:
    """Pose (R, T) of a device at ``eye_mm`` looking at ``target_mm`` (world frame, mm).

    The device's +z points at the target, +y points roughly along ``up`` negated (image rows go down).
    """
    eye = np.asarray(eye_mm, dtype=np.float64)
    z = np.asarray(target_mm, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    upv = np.array([0.0, -1.0, 0.0]) if up is None else np.asarray(up, dtype=np.float64)
    x = np.cross(z, upv)
    if np.linalg.norm(x) < 1e-9:
        raise CalibrationError("look_at: 'up' is parallel to the viewing direction; choose another up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    T = -R @ eye
    return R, T
