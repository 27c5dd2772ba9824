"""Accuracy of a reconstructed cloud against the virtual rig's ground truth."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from appliance.reconstruct.types import PointCloud

if TYPE_CHECKING:
    from appliance.sim.rig import VirtualRig


@dataclass(frozen=True)
class AccuracyReport:
    """Per-point error statistics against ground truth.

    Attributes
    ----------
    points : int
        Points compared.
    rms_mm, median_mm, p99_mm, max_mm : float
        Euclidean distance from each point to the true surface point of its camera pixel (mm).
    share_over_1mm : float
        Fraction (0..1) of points more than 1 mm from the truth.
    completeness : float
        Fraction (0..1) of lit, unshadowed pixels that produced a point.
    """

    points: int
    rms_mm: float
    median_mm: float
    p99_mm: float
    max_mm: float
    share_over_1mm: float
    completeness: float

    def line(self) -> str:
        """A one-line human summary."""
        return (
            f"{self.points} points: RMS {self.rms_mm:.3f} mm, median {self.median_mm:.3f} mm, "
            f"p99 {self.p99_mm:.3f} mm, {100 * self.share_over_1mm:.4f} % over 1 mm, "
            f"completeness {100 * self.completeness:.2f} %"
        )


def compare_to_ground_truth(cloud: PointCloud, rig: VirtualRig, cameras: list[str]) -> AccuracyReport:
    """Compare ``cloud`` with the ground truth of ``rig`` (a VirtualRig).

    Parameters
    ----------
    cloud : PointCloud
        Points with their source camera index and pixel.
    rig : VirtualRig
        The rig that rendered the scan.
    cameras : list of str
        Camera names in the order of ``cloud.camera`` indices.
    """
    errors = []
    lit_total = 0
    lit_hit = 0
    for idx, name in enumerate(cameras):
        gt = rig.ground_truth(name)
        sel = cloud.camera == idx
        r, c = cloud.row[sel], cloud.col[sel]
        truth = gt.xyz[r, c]
        ok = np.isfinite(truth).all(axis=1)
        errors.append(np.linalg.norm(cloud.xyz[sel][ok].astype(np.float64) - truth[ok], axis=1))
        # a point on a pixel without a true surface is an outlier of infinite error
        errors.append(np.full(int((~ok).sum()), np.inf))
        lit_total += int(gt.lit.sum())
        lit_hit += int(gt.lit[r, c].sum())
    e = np.concatenate(errors) if errors else np.zeros(0)
    if e.size == 0:
        return AccuracyReport(0, float("nan"), float("nan"), float("nan"), float("nan"), float("nan"), 0.0)
    finite = e[np.isfinite(e)]
    return AccuracyReport(
        points=int(e.size),
        rms_mm=float(np.sqrt(np.mean(finite**2))) if finite.size else float("inf"),
        median_mm=float(np.median(e)),
        p99_mm=float(np.percentile(e, 99)),
        max_mm=float(e.max()),
        share_over_1mm=float(np.mean(e > 1.0)),
        completeness=lit_hit / lit_total if lit_total else 0.0,
    )


def normal_errors_deg(cloud: PointCloud, rig: VirtualRig, cameras: list[str]) -> npt.NDArray[np.float64]:
    """Angle between each point's estimated normal and the true surface normal of its pixel.

    Parameters
    ----------
    cloud : PointCloud
        Points with normals (``cloud.normal`` not None), source camera index and pixel.
    rig : VirtualRig
        The rig that rendered the scan.
    cameras : list of str
        Camera names in the order of ``cloud.camera`` indices.

    Returns
    -------
    ndarray, shape (N,), float64
        Angles (degrees, 0..180: both normals face the camera, so a flipped one is ~180) in the order of the
        cloud's points; NaN where either normal is missing.
    """
    if cloud.normal is None:
        raise ValueError("normal_errors_deg: the cloud has no normals (set reconstruction.normals: true)")
    out = np.full(len(cloud.xyz), np.nan)
    for idx, name in enumerate(cameras):
        gt = rig.ground_truth(name)
        sel = np.flatnonzero(cloud.camera == idx)
        truth = gt.normal[cloud.row[sel], cloud.col[sel]]
        cos = np.sum(cloud.normal[sel].astype(np.float64) * truth, axis=1)  # both face the camera
        out[sel] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out
