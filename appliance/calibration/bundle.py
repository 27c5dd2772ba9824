"""Joint refinement of every device of a rig (bundle adjustment over cameras, projector and board poses).

Unknowns: each device's intrinsics (fx, fy, cx, cy and the free distortion coefficients of its model),
each non-reference device's pose (world -> device), and each board pose (board -> world; the world is
the reference camera). Observations: board points seen by a device in a view (a projector "sees" the
corners through a camera's decoding; several cameras give several projector observations of one pose).
The reprojection error of all observations is minimised together by Levenberg-Marquardt with the
analytic Jacobian from OpenCV (``projectPoints`` and ``composeRT``); the normal equations are small
(a few hundred unknowns), so they are solved densely.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from appliance.calibration._kernels import cholesky_solve
from appliance.calibration.intrinsics import MODEL_ALIASES, model_flags
from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel

F64 = npt.NDArray[np.float64]

MAX_ITERATIONS = 100
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
CONVERGED_REL = 1e-10
"""Levenberg-Marquardt stops when a step lowers the cost by less than this share."""
OUTLIER_SIGMAS = 5.0
"""After a first solve, points whose residual exceeds this many robust sigmas (and 1 px) are dropped."""


def free_distortion(model: str) -> tuple[int, tuple[int, ...]]:
    """Length of the distortion vector and the indices the model estimates (OpenCV order)."""
    name = MODEL_ALIASES.get(model, model)
    model_flags(name)  # validates the name
    table: dict[str, tuple[int, tuple[int, ...]]] = {
        "none": (5, ()), "k1": (5, (0,)), "k2": (5, (0, 1)), "k2p": (5, (0, 1, 2, 3)),
        "k3": (5, (0, 1, 4)), "k3p": (5, (0, 1, 2, 3, 4)), "rational": (8, tuple(range(8))),
    }  # fmt: skip
    return table[name]


@dataclass(frozen=True)
class Observation:
    """Board points seen by one device in one view.

    Attributes
    ----------
    device : str
        Device name.
    view : int
        Board pose index.
    object_points : ndarray, shape (N, 3)
        Board-frame points (mm).
    image_points : ndarray, shape (N, 2)
        Observed pixels (px) in the device's image.
    source : str
        Where the observation came from (the decoding camera for a projector).
    """

    device: str
    view: int
    object_points: F64
    image_points: F64
    source: str = ""


@dataclass
class BundleResult:
    """The refined rig.

    Attributes
    ----------
    devices : dict of str to CameraModel
        Refined devices with their poses (world = the reference camera); ``rms`` per device.
    board_poses : dict of int to (ndarray (3,), ndarray (3,))
        Board pose of each view: Rodrigues vector and translation, board -> world (mm).
    rms : float
        Reprojection RMS over all kept observations (px).
    std_devs : dict of str to dict of str to float
        Per device: standard deviation of ``fx fy cx cy``, the free distortion coefficients and, for
        non-reference devices, ``rx ry rz`` (rad) and ``tx ty tz`` (mm).
    residuals : list of ndarray
        Per observation (in input order): (N, 2) observed minus reprojected (px); NaN rows were dropped
        as outliers.
    iterations : int
        Levenberg-Marquardt iterations.
    dropped_points : int
        Points dropped as outliers.
    correlations : dict of str to dict of str to (str, float)
        Per device and free intrinsic parameter: the other intrinsic of the same device it correlates with
        most strongly, and that correlation coefficient (-1..1).
    fixed : tuple of str
        Devices whose intrinsics were held at their starting values.
    """

    devices: dict[str, CameraModel]
    board_poses: dict[int, tuple[F64, F64]]
    rms: float
    std_devs: dict[str, dict[str, float]]
    residuals: list[F64] = field(default_factory=list)
    iterations: int = 0
    dropped_points: int = 0
    correlations: dict[str, dict[str, tuple[str, float]]] = field(default_factory=dict)
    fixed: tuple[str, ...] = ()


class _Layout:
    """Where each unknown lives in the parameter vector."""

    def __init__(
        self,
        devices: dict[str, CameraModel],
        models: dict[str, str],
        views: list[int],
        fixed: Collection[str] = (),
    ) -> None:
        self.names = list(devices)
        self.ref = self.names[0]
        self.dist_len: dict[str, int] = {}
        self.dist_free: dict[str, tuple[int, ...]] = {}
        self.intr: dict[str, int] = {}
        self.pose: dict[str, int] = {}
        self.view: dict[int, int] = {}
        self.fixed = {n: (devices[n].K.copy(), devices[n].dist.copy()) for n in fixed if n in devices}
        k = 0
        for n in self.names:
            self.dist_len[n], self.dist_free[n] = free_distortion(models[n])
            self.intr[n] = k
            k += self.n_intr(n)
        for n in self.names[1:]:
            self.pose[n] = k
            k += 6
        for v in views:
            self.view[v] = k
            k += 6
        self.size = k

    def n_intr(self, name: str) -> int:
        return 0 if name in self.fixed else 4 + len(self.dist_free[name])

    def intrinsics(self, x: F64, name: str) -> tuple[F64, F64]:
        if name in self.fixed:
            return self.fixed[name]
        i = self.intr[name]
        K = np.array([[x[i], 0.0, x[i + 2]], [0.0, x[i + 1], x[i + 3]], [0.0, 0.0, 1.0]])
        d = np.zeros(self.dist_len[name])
        d[list(self.dist_free[name])] = x[i + 4 : i + self.n_intr(name)]
        return K, d


def _rvec(R: F64) -> F64:
    import cv2

    r, _ = cv2.Rodrigues(np.asarray(R, np.float64))
    return np.asarray(r, np.float64).ravel()


def _rmat(r: F64) -> F64:
    import cv2

    R, _ = cv2.Rodrigues(np.asarray(r, np.float64).reshape(3, 1))
    return np.asarray(R, np.float64)


def _evaluate(
    x: F64, lay: _Layout, obs: Sequence[Observation], keep: list[npt.NDArray[np.bool_]], jac: bool
) -> tuple[F64, tuple[F64, F64] | None]:
    """Residuals, and with ``jac`` the normal equations ``(J^T J, J^T r)``.

    Each observation touches only its device's intrinsics and pose and its view's board pose, so the normal
    equations are accumulated block by block instead of from a dense Jacobian.
    """
    import cv2

    rows = sum(2 * int(k.sum()) for k in keep)
    r = np.empty(rows)
    A = np.zeros((lay.size, lay.size)) if jac else None
    g = np.zeros(lay.size) if jac else None
    at = 0
    for o, k in zip(obs, keep, strict=True):
        m = int(k.sum())
        if m == 0:
            continue
        K, d = lay.intrinsics(x, o.device)
        vi = lay.view[o.view]
        rv, tv = x[vi : vi + 3], x[vi + 3 : vi + 6]
        if o.device == lay.ref:
            r3, t3 = rv, tv
            comp = None
        else:
            pi = lay.pose[o.device]
            comp = cv2.composeRT(rv, tv, x[pi : pi + 3], x[pi + 3 : pi + 6])
            r3, t3 = np.asarray(comp[0], np.float64).ravel(), np.asarray(comp[1], np.float64).ravel()
        px, jp = cv2.projectPoints(o.object_points[k].reshape(-1, 1, 3), r3, t3, K, d)
        sl = slice(at, at + 2 * m)
        r[sl] = (px.reshape(-1, 2) - o.image_points[k]).ravel()
        if A is not None and g is not None:
            jd: F64 = np.asarray(jp, np.float64)
            Jr, Jt = jd[:, 0:3], jd[:, 3:6]
            blocks: list[F64] = []
            cols: list[int] = []
            ii = lay.intr[o.device]
            if o.device not in lay.fixed:
                free = list(lay.dist_free[o.device])
                blocks += [jd[:, 6:8], jd[:, 8:10], jd[:, 10:][:, free]]
                cols += list(range(ii, ii + lay.n_intr(o.device)))
            if comp is None:
                blocks += [Jr, Jt]
            else:
                _, _, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = comp
                blocks += [Jr @ dr3dr1 + Jt @ dt3dr1, Jr @ dr3dt1 + Jt @ dt3dt1]
            cols += list(range(vi, vi + 6))
            if comp is not None:
                pi = lay.pose[o.device]
                blocks += [Jr @ dr3dr2 + Jt @ dt3dr2, Jr @ dr3dt2 + Jt @ dt3dt2]
                cols += list(range(pi, pi + 6))
            Jl = np.concatenate(blocks, axis=1)
            idx = np.asarray(cols)
            A[np.ix_(idx, idx)] += Jl.T @ Jl
            g[idx] += Jl.T @ r[sl]
        at += 2 * m
    return r, (A, g) if A is not None and g is not None else None


def _levenberg_marquardt(
    x: F64,
    lay: _Layout,
    obs: Sequence[Observation],
    keep: list[npt.NDArray[np.bool_]],
    rel_tol: float,
    max_iterations: int = MAX_ITERATIONS,
) -> tuple[F64, F64, int]:
    """Minimise the squared residuals from ``x``; returns x, the final ``J^T J`` and the iterations."""
    lam = 1e-3
    r, ne = _evaluate(x, lay, obs, keep, True)
    assert ne is not None
    A, g = ne
    cost = float(r @ r)
    it = 0
    while it < max_iterations:
        it += 1
        diag = np.maximum(np.diag(A).copy(), 1e-12)
        improved = False
        while lam < 1e12:
            ok, sol = cholesky_solve(A + lam * np.diag(diag), -g.reshape(-1, 1))
            if not ok:
                lam *= 10.0
                continue
            dx = sol.ravel()
            r_new, _ = _evaluate(x + dx, lay, obs, keep, False)
            c_new = float(r_new @ r_new)
            if np.isfinite(c_new) and c_new < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        x = x + dx
        rel = (cost - c_new) / max(cost, 1e-300)
        cost = c_new
        lam = max(lam / 10.0, 1e-12)
        r, ne = _evaluate(x, lay, obs, keep, True)
        assert ne is not None
        A, g = ne
        if rel < rel_tol or float(np.max(np.abs(dx) / (np.abs(x) + 1e-6))) < 1e-12:
            break
    return x, A, it


def bundle_adjust(
    devices: dict[str, CameraModel],
    models: dict[str, str],
    observations: Sequence[Observation],
    board_poses: dict[int, tuple[F64, F64]],
    *,
    reject_outliers: bool = True,
    fixed: Collection[str] = (),
    rel_tol: float = CONVERGED_REL,
    max_iterations: int = MAX_ITERATIONS,
    covariance: bool = True,
) -> BundleResult:
    """Refine all devices' intrinsics and poses and all board poses together.

    Parameters
    ----------
    devices : dict of str to CameraModel
        Initial devices; the first is the reference (its pose stays the identity), the others carry
        their initial pose (world -> device).
    models : dict of str to str
        Distortion model of each device (:data:`~appliance.calibration.intrinsics.DISTORTION_MODELS`).
    observations : sequence of Observation
        Board points per device and view.
    board_poses : dict of int to (ndarray (3,), ndarray (3,))
        Initial board pose per view (Rodrigues vector, translation mm; board -> world); views without
        a pose are ignored.
    reject_outliers : bool
        Drop points beyond ``OUTLIER_SIGMAS`` robust sigmas after a first solve and solve again.
    fixed : collection of str
        Devices whose intrinsics and distortion stay as given (only their poses are refined).
    rel_tol : float
        Stop when a step lowers the cost by less than this share (looser for quick re-solves from a
        nearby start, e.g. leaving one view out).
    max_iterations : int
        Levenberg-Marquardt iterations at most (per solve).
    covariance : bool
        Compute standard deviations and correlations (otherwise they are NaN / empty, and a poorly
        determined problem is not an error).

    Returns
    -------
    BundleResult

    Raises
    ------
    CalibrationError
        No usable observation, or the normal equations are singular.
    """
    obs = [o for o in observations if o.view in board_poses and o.device in devices]
    if not obs:
        raise CalibrationError("joint refinement: no observation with an initial board pose")
    missing = [n for n in devices if not any(o.device == n for o in obs)]
    if missing:
        raise CalibrationError(
            f"joint refinement: device(s) {missing} have no observation; capture more poses"
        )
    views = sorted({o.view for o in obs})
    lay = _Layout(devices, models, views, fixed)
    x = np.zeros(lay.size)
    for n, dev in devices.items():
        i = lay.intr[n]
        if n not in lay.fixed:
            x[i : i + 4] = dev.K[0, 0], dev.K[1, 1], dev.K[0, 2], dev.K[1, 2]
            dist = np.zeros(lay.dist_len[n])
            dist[: min(dev.dist.size, dist.size)] = dev.dist[: dist.size]
            x[i + 4 : i + lay.n_intr(n)] = dist[list(lay.dist_free[n])]
        if n in lay.pose:
            p = lay.pose[n]
            x[p : p + 3], x[p + 3 : p + 6] = _rvec(dev.R), dev.T
    for v in views:
        i = lay.view[v]
        x[i : i + 3], x[i + 3 : i + 6] = board_poses[v][0], board_poses[v][1]
    keep = [np.ones(len(o.object_points), bool) for o in obs]
    x, JtJ, iters = _levenberg_marquardt(x, lay, obs, keep, rel_tol, max_iterations)
    dropped = 0
    if reject_outliers:
        r, _ = _evaluate(x, lay, obs, keep, False)
        err = np.hypot(r[0::2], r[1::2])
        limit = max(OUTLIER_SIGMAS * 1.4826 * float(np.median(err)), 1.0)
        at = 0
        for k in keep:
            m = int(k.sum())
            bad = err[at : at + m] > limit
            k[np.flatnonzero(k)[bad]] = False
            dropped += int(bad.sum())
            at += m
        if dropped:
            x, JtJ, more = _levenberg_marquardt(x, lay, obs, keep, rel_tol, max_iterations)
            iters += more
    r, _ = _evaluate(x, lay, obs, keep, False)
    n_res = r.size
    sigma2 = float(r @ r) / max(n_res - lay.size, 1)
    ok, inv = cholesky_solve(np.ascontiguousarray(JtJ), np.eye(lay.size)) if covariance else (True, None)
    if inv is None:
        inv = np.full((lay.size, lay.size), np.nan)
    elif not ok:
        raise CalibrationError(
            "joint refinement: the problem is degenerate (singular normal equations); "
            "add board poses with more tilt"
        )
    cov = inv * sigma2
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out_devices: dict[str, CameraModel] = {}
    std: dict[str, dict[str, float]] = {}
    corr: dict[str, dict[str, tuple[str, float]]] = {}
    residuals: list[F64] = []
    per_dev: dict[str, list[F64]] = {n: [] for n in devices}
    at = 0
    for o, k in zip(obs, keep, strict=True):
        res = np.full((len(k), 2), np.nan)
        m = int(k.sum())
        res[k] = -r[at : at + 2 * m].reshape(-1, 2)
        residuals.append(res)
        per_dev[o.device].append(res[k])
        at += 2 * m
    for n, dev in devices.items():
        K, d = lay.intrinsics(x, n)
        R, T = np.eye(3), np.zeros(3)
        i = lay.intr[n]
        names = [] if n in lay.fixed else ["fx", "fy", "cx", "cy", *(DIST_NAMES[j] for j in lay.dist_free[n])]
        std[n] = {nm: float(sd[i + j]) for j, nm in enumerate(names)}
        corr[n] = _strongest_correlations(np.asarray(cov[i : i + len(names), i : i + len(names)], np.float64), names)
        if n in lay.pose:
            p = lay.pose[n]
            R, T = _rmat(x[p : p + 3]), x[p + 3 : p + 6].copy()
            for j, nm in enumerate(("rx", "ry", "rz", "tx", "ty", "tz")):
                std[n][nm] = float(sd[p + j])
        e = np.concatenate(per_dev[n]) if per_dev[n] else np.zeros((0, 2))
        rms = float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) if len(e) else float("nan")
        out_devices[n] = CameraModel(n, K, d, dev.width, dev.height, R, T, rms=rms)
    poses = {
        v: (x[lay.view[v] : lay.view[v] + 3].copy(), x[lay.view[v] + 3 : lay.view[v] + 6].copy())
        for v in views
    }
    total = float(np.sqrt(np.mean(r[0::2] ** 2 + r[1::2] ** 2)))
    # residuals align with the filtered observation list; map back to the input order
    full: list[F64] = []
    it_res = iter(residuals)
    for o in observations:
        if o.view in board_poses and o.device in devices:
            full.append(next(it_res))
        else:
            full.append(np.full((len(o.object_points), 2), np.nan))
    return BundleResult(out_devices, poses, total, std, full, iters, dropped, corr, tuple(lay.fixed))


def _strongest_correlations(cov: F64, names: Sequence[str]) -> dict[str, tuple[str, float]]:
    """Per parameter: the other parameter it correlates with most strongly, and the coefficient."""
    if len(names) < 2:
        return {}
    s = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    c = cov / np.outer(s, s)
    np.fill_diagonal(c, 0.0)
    out = {}
    for j, nm in enumerate(names):
        k = int(np.argmax(np.abs(c[j])))
        out[nm] = (names[k], float(np.clip(c[j, k], -1.0, 1.0)))
    return out
