"""Calibration verification in the spirit of VDI/VDE 2634: form fits of a scanned known artefact.

Flatness is the peak-to-valley distance of the points from their least-squares plane (mm); a sphere's
diameter comes from an algebraic least-squares sphere fit (mm). The scan of the artefact itself
(``verify_cli``) is not implemented yet.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from appliance.errors import CalibrationError

F64 = npt.NDArray[np.float64]


def fit_plane(xyz: F64) -> tuple[F64, float, float]:
    """Least-squares plane of points.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Points (mm), N >= 3.

    Returns
    -------
    normal : ndarray, shape (3,)
        Unit normal.
    offset : float
        ``normal . x = offset`` on the plane (mm).
    flatness : float
        Peak-to-valley distance of the points from the plane (mm).
    """
    p = np.asarray(xyz, np.float64).reshape(-1, 3)
    if len(p) < 3:
        raise CalibrationError(f"plane fit: {len(p)} points; need >= 3")
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[2]
    d = (p - c) @ n
    return n, float(n @ c), float(d.max() - d.min())


def fit_sphere(xyz: F64) -> tuple[F64, float, float]:
    """Least-squares sphere of points (algebraic fit).

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Points (mm), N >= 4.

    Returns
    -------
    centre : ndarray, shape (3,)
        Centre (mm).
    radius : float
        Radius (mm).
    rms : float
        RMS of the radial residuals (mm).
    """
    p = np.asarray(xyz, np.float64).reshape(-1, 3)
    if len(p) < 4:
        raise CalibrationError(f"sphere fit: {len(p)} points; need >= 4")
    m = p.mean(axis=0)
    q = p - m
    A = np.concatenate([2 * q, np.ones((len(q), 1))], axis=1)
    sol, *_ = np.linalg.lstsq(A, (q * q).sum(axis=1), rcond=None)
    centre = sol[:3]
    radius = float(np.sqrt(sol[3] + centre @ centre))
    res = np.linalg.norm(q - centre, axis=1) - radius
    return centre + m, radius, float(np.sqrt(np.mean(res * res)))


def verify_cli(config: Path | None) -> int:
    """``scan3d verify``: scan the configured artefact and check the calibration.

    Raises
    ------
    CalibrationError
        Always, for now: the artefact scan is not implemented yet.
    """
    raise CalibrationError(
        "verify: scanning the reference artefact is not implemented yet; "
        "use appliance.calibration.verify.fit_plane / fit_sphere on a scanned cloud"
    )
