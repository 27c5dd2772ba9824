"""Calibration verification after VDI/VDE 2634 part 2: the figures of scans of a known artefact.

The quantities of VDI/VDE 2634-2, measured on the artefact in several positions through the measuring volume
(``calibration.artefact.positions``) and compared with maximum permissible errors
(``calibration.tolerances``): probing error form PF (peak-to-valley of a sphere's radial residuals), probing
error size PS (fitted minus calibrated diameter), sphere-spacing error SD (measured minus calibrated centre
distance of the ball bar) and the flatness of the plane. The scans themselves are taken by
:mod:`appliance.procedures.verify`; this module has the fits, the figures and the report page.

The artefact (``calibration.artefact``) is a ball bar (two or more calibrated spheres) and a flat. Points are
segmented by proximity to the nominal sphere centres and the nominal plane; each sphere is fitted robustly
(algebraic start, geometric least squares, residuals beyond 3 robust sigmas trimmed) and compared with its
calibrated diameter; the centre distance of the first two spheres is the ball-bar length. Flatness is the
peak-to-valley of the plane residuals after excluding the largest 0.3 % (VDI/VDE 2634). The raw value
contains the scanner's point noise; the value checked against ``flatness_mm`` averages the residuals over
cells of ``flatness_cell_mm`` first, so it measures the plane's *form* (what a wrong calibration bends)
rather than the noise. On a virtual rig the artefact is put into the scene from its description.
"""

from __future__ import annotations

import html
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.atomic_write import write_bytes_atomic
from appliance.config.schema import (
    ArtefactConfig,
    ArtefactPlane,
    ArtefactPosition,
    ArtefactSphere,
    PlaneObject,
    SphereObject,
    VerifyTolerances,
)
from appliance.errors import CalibrationError, OutputError

F64 = npt.NDArray[np.float64]
SEARCH_FACTOR = 3.0
"""The first, wide segmentation reaches this many ``search_margin_mm`` beyond the nominal surfaces."""


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


def fit_sphere_robust(
    xyz: F64, trim_sigmas: float = 3.0, iterations: int = 5
) -> tuple[F64, float, float, npt.NDArray[np.bool_]]:
    """Sphere fit that ignores outliers (mixed pixels at the silhouette, stray points).

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Points (mm), N >= 4.
    trim_sigmas : float
        Points whose radial residual exceeds this many robust sigmas (1.4826 MAD) are dropped.
    iterations : int
        Trim-and-refit rounds.

    Returns
    -------
    centre : ndarray, shape (3,)
        Centre (mm).
    radius : float
        Radius (mm), from a geometric (orthogonal distance) least-squares fit of the inliers.
    rms : float
        RMS radial residual of the inliers (mm).
    inliers : ndarray, shape (N,), bool
    """
    p = np.asarray(xyz, np.float64).reshape(-1, 3)
    centre, radius, _ = fit_sphere(p)
    keep = np.ones(len(p), bool)
    for _ in range(iterations):
        centre, radius = _geometric_sphere(p[keep], centre, radius)
        res = np.linalg.norm(p - centre, axis=1) - radius
        sigma = max(1.4826 * float(np.median(np.abs(res[keep]))), 1e-6)
        new = np.abs(res) <= trim_sigmas * sigma
        if new.sum() < 4 or np.array_equal(new, keep):
            break
        keep = new
    centre, radius = _geometric_sphere(p[keep], centre, radius)
    res = np.linalg.norm(p[keep] - centre, axis=1) - radius
    return centre, radius, float(np.sqrt(np.mean(res * res))), keep


def _geometric_sphere(p: F64, centre: F64, radius: float) -> tuple[F64, float]:
    """Gauss-Newton on the orthogonal distances, from an algebraic start."""
    c, r = np.asarray(centre, np.float64).copy(), float(radius)
    for _ in range(10):
        d = p - c
        dist = np.linalg.norm(d, axis=1)
        res = dist - r
        J = np.concatenate([-d / dist[:, None], -np.ones((len(p), 1))], axis=1)
        step, *_ = np.linalg.lstsq(J, -res, rcond=None)
        c += step[:3]
        r += float(step[3])
        if np.abs(step).max() < 1e-9:
            break
    return c, r


def _exclude(values: F64, fraction: float) -> F64:
    """``values`` without the ``fraction`` of largest magnitudes."""
    n_drop = int(np.floor(fraction * len(values)))
    if n_drop == 0:
        return values
    return values[np.argsort(np.abs(values))[: len(values) - n_drop]]


@dataclass(frozen=True)
class Check:
    """One pass/fail line: ``value`` (mm) against ``limit`` (mm)."""

    name: str
    value: float
    limit: float

    @property
    def passed(self) -> bool:
        """True when ``|value| <= limit``."""
        return bool(np.isfinite(self.value) and abs(self.value) <= self.limit)


@dataclass
class VerifyReport:
    """Result of a verification scan.

    Attributes
    ----------
    spheres : list of dict
        Per sphere: ``points``, ``centre_mm``, ``diameter_mm``, ``nominal_mm``, ``error_mm`` (PS),
        ``rms_mm``, ``form_mm`` (PF: peak-to-valley of the radial residuals).
    ball_bar : dict or None
        ``measured_mm``, ``nominal_mm``, ``error_mm`` of the first two spheres' centre distance.
    plane : dict or None
        ``points``, ``flatness_mm`` (cell means), ``flatness_raw_mm`` (points), ``rms_mm``.
    checks : list of Check
        Every value compared with its tolerance.
    """

    spheres: list[dict[str, Any]] = field(default_factory=list)
    ball_bar: dict[str, float] | None = None
    plane: dict[str, float] | None = None
    checks: list[Check] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        """True when every check passed (and there was at least one)."""
        return bool(self.checks) and all(c.passed for c in self.checks)

    def lines(self) -> list[str]:
        """Human report, one line per measured quantity, then PASS or FAIL."""
        out = []
        for i, s in enumerate(self.spheres):
            out.append(
                f"sphere {i}: {s['points']} points, diameter {s['diameter_mm']:.4f} mm (calibrated "
                f"{s['nominal_mm']:.4f}), error {s['error_mm']:+.4f} mm, form RMS {s['rms_mm']:.4f} mm, "
                f"form PV {s['form_mm']:.4f} mm"
            )
        if self.ball_bar is not None:
            b = self.ball_bar
            out.append(f"ball bar: length {b['measured_mm']:.4f} mm (calibrated {b['nominal_mm']:.4f}), "
                       f"error {b['error_mm']:+.4f} mm")  # fmt: skip
        if self.plane is not None:
            p = self.plane
            out.append(f"plane: {int(p['points'])} points, flatness {p['flatness_mm']:.4f} mm (cell means), "
                       f"{p['flatness_raw_mm']:.4f} mm (points, noise included), "
                       f"RMS {p['rms_mm']:.4f} mm")  # fmt: skip
        for c in self.checks:
            out.append(
                f"  {'pass' if c.passed else 'FAIL'}: {c.name} {c.value:+.4f} mm (limit {c.limit:.4f} mm)"
            )
        out.append("PASS" if self.passed else "FAIL")
        return out


def evaluate_artefact(xyz: F64, artefact: ArtefactConfig, tol: VerifyTolerances) -> VerifyReport:
    """Segment, fit and check a scan of the artefact.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Scanned points, world frame (mm).
    artefact : ArtefactConfig
        Nominal spheres and plane.
    tol : VerifyTolerances
        Limits.

    Returns
    -------
    VerifyReport

    Raises
    ------
    CalibrationError
        When a sphere or the plane has too few points (artefact not where the configuration says).
    """
    p = np.asarray(xyz, np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    rep = VerifyReport()
    margin = artefact.search_margin_mm
    centres = []
    near_sphere = np.zeros(len(p), bool)
    for i, sph in enumerate(artefact.spheres):
        c0 = np.asarray(sph.center_mm, np.float64)
        r0 = sph.diameter_mm / 2
        # wide search around the nominal centre, then the points near the fitted surface
        sel = np.linalg.norm(p - c0, axis=1) < r0 + SEARCH_FACTOR * margin
        if sel.sum() < 50:
            raise CalibrationError(
                f"verify: sphere {i} (centre {sph.center_mm} mm, diameter {sph.diameter_mm} mm): only "
                f"{int(sel.sum())} points within {r0 + SEARCH_FACTOR * margin:.1f} mm of its centre; "
                "place the "
                "artefact at its nominal position (calibration.artefact) or raise search_margin_mm"
            )
        centre, radius, _, _ = fit_sphere_robust(p[sel])
        dist = np.linalg.norm(p - centre, axis=1)
        near_sphere |= dist < radius + 2 * margin
        sel = np.abs(dist - radius) < margin
        centre, radius, rms, keep = fit_sphere_robust(p[sel])
        err = 2 * radius - sph.diameter_mm
        radial = _exclude(np.linalg.norm(p[sel][keep] - centre, axis=1) - radius, tol.exclude_fraction)
        form = float(radial.max() - radial.min())
        rep.spheres.append({"points": int(keep.sum()), "centre_mm": centre.tolist(),
                            "diameter_mm": 2 * radius, "nominal_mm": sph.diameter_mm, "error_mm": err,
                            "rms_mm": rms, "form_mm": form})  # fmt: skip
        rep.checks.append(Check(f"PF sphere {i} probing form", form, tol.probing_form_mm))
        rep.checks.append(Check(f"PS sphere {i} diameter error", err, tol.sphere_diameter_mm))
        centres.append(centre)
    if len(centres) >= 2:
        s0, s1 = artefact.spheres[0], artefact.spheres[1]
        nominal = artefact.ball_bar_length_mm
        if nominal is None:
            nominal = float(np.linalg.norm(np.subtract(s1.center_mm, s0.center_mm)))
        measured = float(np.linalg.norm(centres[1] - centres[0]))
        rep.ball_bar = {"measured_mm": measured, "nominal_mm": nominal, "error_mm": measured - nominal}
        rep.checks.append(Check("SD sphere spacing (ball-bar length) error", measured - nominal,
                                tol.ball_bar_length_mm))  # fmt: skip
    if artefact.plane is not None:
        rep.plane = _plane(p, near_sphere, artefact, tol)
        rep.checks.append(Check("plane flatness", rep.plane["flatness_mm"], tol.flatness_mm))
    return rep


def _plane(
    p: F64, near_sphere: npt.NDArray[np.bool_], artefact: ArtefactConfig, tol: VerifyTolerances
) -> dict[str, float]:
    pl = artefact.plane
    assert pl is not None
    n0 = np.asarray(pl.normal, np.float64)
    n0 /= np.linalg.norm(n0)
    a = np.cross(n0, [1.0, 0.0, 0.0] if abs(n0[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n0, a)
    q = p - np.asarray(pl.point_mm)
    s, t = q @ a, q @ b
    sel = (np.abs(q @ n0) < SEARCH_FACTOR * artefact.search_margin_mm) & ~near_sphere
    # the extent is given along the world-aligned in-plane axes; accept either orientation of the rectangle
    half = np.asarray(pl.size_mm) / 2
    sel &= (
        (np.abs(s) <= max(half)) & (np.abs(t) <= max(half)) & (np.minimum(np.abs(s), np.abs(t)) <= min(half))
    )
    if sel.sum() < 100:
        raise CalibrationError(
            f"verify: plane (point {pl.point_mm} mm): only {int(sel.sum())} points within "
            f"{artefact.search_margin_mm} mm of it; place the artefact at its nominal position"
        )
    normal, offset, _ = fit_plane(p[sel])
    for _ in range(5):  # from the wide band to the points near the fitted plane
        res = p @ normal - offset
        band = sel & (np.abs(res) < artefact.search_margin_mm)
        if band.sum() < 100:
            break
        normal, offset, _ = fit_plane(p[band])
    sel = band
    pts = p[sel]
    res = pts @ normal - offset
    kept = (
        np.abs(res) <= np.sort(np.abs(res))[max(int(np.ceil((1 - tol.exclude_fraction) * len(res))) - 1, 0)]
    )
    normal, offset, _ = fit_plane(pts[kept])  # refit without the excluded points
    res = pts @ normal - offset
    raw = _exclude(res, tol.exclude_fraction)
    out = {"points": float(len(pts)), "flatness_raw_mm": float(raw.max() - raw.min()),
           "rms_mm": float(np.sqrt(np.mean(raw * raw)))}  # fmt: skip
    if tol.flatness_cell_mm > 0:
        cs, ct = np.floor(s[sel] / tol.flatness_cell_mm), np.floor(t[sel] / tol.flatness_cell_mm)
        _, cell = np.unique(np.stack([cs, ct], axis=1), axis=0, return_inverse=True)
        cell = cell.ravel()
        count = np.bincount(cell)
        mean = np.bincount(cell, weights=res) / np.maximum(count, 1)
        means = _exclude(mean[count >= 10], tol.exclude_fraction)
        out["flatness_mm"] = float(means.max() - means.min()) if len(means) else float("nan")
    else:
        out["flatness_mm"] = out["flatness_raw_mm"]
    return out


def artefact_scene(artefact: ArtefactConfig) -> tuple[PlaneObject | SphereObject, ...]:
    """The artefact as virtual-rig scene objects (spheres, then the plane)."""
    objs: list[PlaneObject | SphereObject] = [
        SphereObject(center_mm=s.center_mm, radius_mm=s.diameter_mm / 2, albedo=artefact.albedo)
        for s in artefact.spheres
    ]
    if artefact.plane is not None:
        objs.append(PlaneObject(point_mm=artefact.plane.point_mm, normal=artefact.plane.normal,
                                albedo=artefact.albedo))  # fmt: skip
    return tuple(objs)


def placed(artefact: ArtefactConfig, position: ArtefactPosition) -> ArtefactConfig:
    """The artefact moved to ``position``: turned about the world z axis through its spheres' mean centre,
    then shifted.

    Parameters
    ----------
    artefact : ArtefactConfig
        The artefact at its nominal place.
    position : ArtefactPosition
        Offset (mm) and turn (deg).

    Returns
    -------
    ArtefactConfig
        Same artefact, nominal sphere centres and plane moved (the ball-bar length is unchanged).
    """
    a = np.deg2rad(position.rotation_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    centres = [np.asarray(sp.center_mm, np.float64) for sp in artefact.spheres]
    pivot = np.mean(centres, axis=0) if centres else np.zeros(3)
    off = np.asarray(position.offset_mm, np.float64)

    def move(x: Sequence[float]) -> tuple[float, float, float]:
        v = R @ (np.asarray(x, np.float64) - pivot) + pivot + off
        return (float(v[0]), float(v[1]), float(v[2]))

    spheres = tuple(ArtefactSphere(center_mm=move(sp.center_mm), diameter_mm=sp.diameter_mm)
                    for sp in artefact.spheres)  # fmt: skip
    plane = None
    if artefact.plane is not None:
        n = R @ np.asarray(artefact.plane.normal, np.float64)
        plane = ArtefactPlane(point_mm=move(artefact.plane.point_mm), normal=(float(n[0]), float(n[1]), float(n[2])),
                              size_mm=artefact.plane.size_mm)  # fmt: skip
    nominal = artefact.ball_bar_length_mm
    if nominal is None and len(centres) >= 2:
        nominal = float(np.linalg.norm(centres[1] - centres[0]))
    return artefact.model_copy(update={"spheres": spheres, "plane": plane, "ball_bar_length_mm": nominal})


@dataclass
class VdiReport:
    """VDI/VDE 2634-2 figures over all positions of the artefact.

    Attributes
    ----------
    positions : list of ArtefactPosition
        Where the artefact was.
    reports : list of VerifyReport
        One per position.
    tolerances : VerifyTolerances
        The maximum permissible errors.
    """

    positions: list[ArtefactPosition]
    reports: list[VerifyReport]
    tolerances: VerifyTolerances

    def figures(self) -> dict[str, float]:
        """``PF``, ``PS``, ``SD`` and ``flatness``: the worst value over all positions (mm; PS and SD signed)."""

        def worst(values: list[float]) -> float:
            vals = [v for v in values if np.isfinite(v)]
            return max(vals, key=abs) if vals else float("nan")

        return {
            "PF": worst([s["form_mm"] for r in self.reports for s in r.spheres]),
            "PS": worst([s["error_mm"] for r in self.reports for s in r.spheres]),
            "SD": worst([r.ball_bar["error_mm"] for r in self.reports if r.ball_bar is not None]),
            "flatness": worst([r.plane["flatness_mm"] for r in self.reports if r.plane is not None]),
        }

    @property
    def checks(self) -> list[Check]:
        """Each figure against its maximum permissible error."""
        f, t = self.figures(), self.tolerances
        out = [Check("PF probing error form", f["PF"], t.probing_form_mm),
               Check("PS probing error size", f["PS"], t.sphere_diameter_mm),
               Check("SD sphere-spacing error", f["SD"], t.ball_bar_length_mm)]  # fmt: skip
        if np.isfinite(f["flatness"]):
            out.append(Check("flatness", f["flatness"], t.flatness_mm))
        return out

    @property
    def passed(self) -> bool:
        """True when every figure is within its maximum permissible error."""
        return all(c.passed for c in self.checks)

    def lines(self) -> list[str]:
        """Human report: each position's measurements, then the figures against the MPEs, then PASS/FAIL."""
        out: list[str] = []
        for k, (pos, rep) in enumerate(zip(self.positions, self.reports, strict=True)):
            out.append(f"position {k + 1} of {len(self.positions)}: offset {tuple(pos.offset_mm)} mm, "
                       f"turned {pos.rotation_deg:+.0f} deg")  # fmt: skip
            out += ["  " + line for line in rep.lines()[:-1] if not line.lstrip().startswith(("pass", "FAIL"))]
        out.append(f"VDI/VDE 2634-2 over {len(self.positions)} positions (worst value, limit = MPE):")
        for c in self.checks:
            out.append(f"  {'pass' if c.passed else 'FAIL'}: {c.name} {c.value:+.4f} mm (MPE {c.limit:.4f} mm)")
        out.append("PASS" if self.passed else "FAIL")
        return out

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready figures, checks and per-position values."""
        return {
            "figures_mm": self.figures(),
            "checks": [{"name": c.name, "value_mm": c.value, "mpe_mm": c.limit, "passed": c.passed}
                       for c in self.checks],
            "positions": [{"offset_mm": list(p.offset_mm), "rotation_deg": p.rotation_deg,
                           "spheres": r.spheres, "ball_bar": r.ball_bar, "plane": r.plane}
                          for p, r in zip(self.positions, self.reports, strict=True)],
            "passed": self.passed,
        }  # fmt: skip


def write_verify_page(path: Path, report: VdiReport, title: str, notes: Sequence[str] = ()) -> Path:
    """Write the verification report page (self-contained HTML with a bar chart per figure).

    Parameters
    ----------
    path : Path
        The page to write.
    report : VdiReport
        The figures.
    title : str
        Page title.
    notes : sequence of str
        Extra lines (e.g. which calibration was checked).

    Returns
    -------
    Path
        ``path``.
    """
    import base64

    from appliance.calibration.report import _png, bar_plot

    t = report.tolerances
    series = {
        "PF probing error form": ([max((s["form_mm"] for s in r.spheres), default=np.nan) for r in report.reports],
                                  t.probing_form_mm),
        "PS probing error size": ([max((s["error_mm"] for s in r.spheres), key=abs, default=np.nan)
                                   for r in report.reports], t.sphere_diameter_mm),
        "SD sphere-spacing error": ([r.ball_bar["error_mm"] if r.ball_bar else np.nan for r in report.reports],
                                    t.ball_bar_length_mm),
        "flatness": ([r.plane["flatness_mm"] if r.plane else np.nan for r in report.reports], t.flatness_mm),
    }  # fmt: skip
    parts = [f"<h1>{html.escape(title)}</h1>"] + [f"<p>{html.escape(n)}</p>" for n in notes]
    rows = "".join(
        f"<tr><td>{html.escape(c.name)}</td><td>{c.value:+.4f}</td><td>{c.limit:.4f}</td>"
        f"<td class='{'ok' if c.passed else 'bad'}'>{'pass' if c.passed else 'FAIL'}</td></tr>"
        for c in report.checks
    )
    parts.append(f"<h2>{'PASS' if report.passed else 'FAIL'}</h2><table><tr><th>figure</th><th>worst (mm)</th>"
                 f"<th>MPE (mm)</th><th></th></tr>{rows}</table>")  # fmt: skip
    labels = [f"#{k + 1}" for k in range(len(report.reports))]
    for name, (values, mpe) in series.items():
        vals = [abs(float(v)) if np.isfinite(v) else 0.0 for v in values]
        img = bar_plot(vals, labels, f"{name} per position, |value| (MPE {mpe:.3f} mm)", unit="mm")
        data = base64.b64encode(_png(img)).decode()
        parts.append(f'<img alt="{html.escape(name)}" src="data:image/png;base64,{data}"><br>')
    parts.append("<h2>Positions</h2><pre>" + html.escape("\n".join(report.lines())) + "</pre>")
    style = "body{font-family:sans-serif} table{border-collapse:collapse} td,th{border:1px solid #999;padding:2px 6px}"
    doc = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>{style}"
           f" .bad{{color:#b00}} .ok{{color:#070}}</style></head><body>{''.join(parts)}</body></html>")  # fmt: skip
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"verify report: cannot write {path} ({exc.strerror}); check permissions") from exc
    return write_bytes_atomic(path, doc.encode("utf-8"))  # a full disk keeps the previous page whole
