"""Calibration report: PNG plots and one self-contained HTML page beside the calibration file.

For ``calibration.yaml`` the report is ``calibration.report.html`` (plots embedded) plus the same plots
as PNG files in ``calibration.report/``: per device the residual vectors over the image, the per-view
errors and the coverage map; the parameters with their standard deviations; stereo extrinsics and RMS.
Plots are drawn with OpenCV (no plotting library needed).
"""

from __future__ import annotations

import base64
import contextlib
import html
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from appliance.calibration.intrinsics import CameraResult
from appliance.calibration.stereo import StereoEntry
from appliance.errors import OutputError

if TYPE_CHECKING:
    from appliance.calibration.boards import BoardSpec
    from appliance.calibration.rig import RigCalibration

U8 = npt.NDArray[np.uint8]
PLOT_WIDTH_PX = 800
_VIEW_COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                 (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]  # fmt: skip


def report_paths(calibration_path: Path) -> tuple[Path, Path]:
    """(HTML page, PNG folder) of the report that belongs to ``calibration_path``."""
    stem = calibration_path.with_suffix("")
    return stem.with_name(stem.name + ".report.html"), stem.with_name(stem.name + ".report")


def _bgr(rgb: tuple[int, int, int]) -> tuple[int, int, int]:
    return (rgb[2], rgb[1], rgb[0])


def residual_plot(result: CameraResult) -> U8:
    """Residual vectors (magnified) at each board point over the device's image, one colour per view."""
    import cv2

    cam = result.camera
    s = PLOT_WIDTH_PX / cam.width
    h = round(cam.height * s)
    img = np.full((h + 30, PLOT_WIDTH_PX, 3), 255, np.uint8)
    cv2.rectangle(img, (0, 0), (PLOT_WIDTH_PX - 1, h - 1), (0, 0, 0), 1)
    allres = np.concatenate(result.residuals) if result.residuals else np.zeros((0, 2))
    p95 = float(np.percentile(np.linalg.norm(allres, axis=1), 95)) if len(allres) else 0.0
    gain = 25.0 / p95 if p95 > 0 else 1.0  # the 95th-percentile residual draws 25 plot px long
    for k, (pts, res) in enumerate(zip(result.image_points, result.residuals, strict=False)):
        colour = _bgr(_VIEW_COLOURS[k % len(_VIEW_COLOURS)])
        for (x, y), (dx, dy) in zip(pts * s, res, strict=False):
            a = (round(x), round(y))
            b = (round(x + dx * gain), round(y + dy * gain))
            cv2.circle(img, a, 2, colour, -1, cv2.LINE_AA)
            cv2.line(img, a, b, colour, 1, cv2.LINE_AA)
    mag = gain * cam.width / PLOT_WIDTH_PX
    text = f"{cam.name}: residuals x{mag:.0f} (p95 {p95:.3f} px), RMS {result.rms:.3f} px"
    cv2.putText(img, text, (5, h + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def bar_plot(values: Sequence[float], labels: Sequence[str], title: str, unit: str = "px") -> U8:
    """A bar chart (e.g. per-view RMS)."""
    import cv2

    n = max(len(values), 1)
    h, top, bottom = 260, 30, 40
    img = np.full((h, PLOT_WIDTH_PX, 3), 255, np.uint8)
    vmax = max([*values, 1e-9]) * 1.15
    bw = (PLOT_WIDTH_PX - 60) / n
    base = h - bottom
    cv2.line(img, (50, base), (PLOT_WIDTH_PX - 5, base), (0, 0, 0), 1)
    cv2.putText(img, title, (5, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, f"{vmax:.3g} {unit}", (2, top + 10), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
    for i, (v, lab) in enumerate(zip(values, labels, strict=False)):
        x0 = int(50 + i * bw + 0.15 * bw)
        x1 = int(50 + (i + 1) * bw - 0.15 * bw)
        y = int(base - (base - top) * v / vmax)
        cv2.rectangle(img, (x0, y), (max(x1, x0 + 1), base), _bgr(_VIEW_COLOURS[i % len(_VIEW_COLOURS)]), -1)
        cv2.putText(img, f"{v:.3f}", (x0, y - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(img, lab, (x0, base + 15), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def coverage_plot(result: CameraResult) -> U8:
    """The coverage map (views covering each image cell) with the board points on top."""
    import cv2

    cam = result.camera
    s = PLOT_WIDTH_PX / cam.width
    h = round(cam.height * s)
    cov = result.coverage.astype(np.float64)
    norm = np.clip(cov / max(float(cov.max()), 1.0) * 255, 0, 255).astype(np.uint8)
    heat = cv2.applyColorMap(
        cv2.resize(norm, (PLOT_WIDTH_PX, h), interpolation=cv2.INTER_NEAREST), cv2.COLORMAP_VIRIDIS
    )
    heat[cv2.resize((cov == 0).astype(np.uint8), (PLOT_WIDTH_PX, h), interpolation=cv2.INTER_NEAREST) > 0] = (
        40
    )
    for pts in result.image_points:
        for x, y in pts * s:
            cv2.circle(heat, (round(x), round(y)), 1, (255, 255, 255), -1)
    img = np.full((h + 30, PLOT_WIDTH_PX, 3), 255, np.uint8)
    img[:h] = heat
    text = (
        f"{cam.name}: coverage {100 * result.coverage_fraction:.0f} % (max {int(cov.max())} views per cell)"
    )
    cv2.putText(img, text, (5, h + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def _png(img: U8) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OutputError("calibration report: PNG encoding failed")
    return bytes(buf.tobytes())


def _param_table(result: CameraResult) -> str:
    cam = result.camera
    values = {"fx": cam.K[0, 0], "fy": cam.K[1, 1], "cx": cam.K[0, 2], "cy": cam.K[1, 2]}
    for name, val in zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), cam.dist, strict=False):
        values[name] = val
    def corr(name: str) -> str:
        if name not in result.correlations:
            return ""
        other, rho = result.correlations[name]
        return f"{rho:+.2f} with {other}"

    rows = "".join(
        f"<tr><td>{n}</td><td>{v:.6g}</td><td>{result.std_devs[n]:.3g}</td><td>{corr(n)}</td></tr>"
        if n in result.std_devs
        else f"<tr><td>{n}</td><td>{v:.6g}</td><td>fixed</td><td></td></tr>"
        for n, v in values.items()
    )
    head = "<tr><th>parameter</th><th>value</th><th>std dev</th><th>strongest correlation</th></tr>"
    return f"<table>{head}{rows}</table>"


def write_report(
    calibration_path: Path,
    devices: Sequence[CameraResult],
    stereo: Sequence[StereoEntry] = (),
    title: str = "Calibration report",
    notes: Sequence[str] = (),
    sections: Sequence[tuple[str, Sequence[str]]] = (),
) -> Path:
    """Write the report of a calibration beside its file.

    Parameters
    ----------
    calibration_path : Path
        The calibration file the report belongs to.
    devices : sequence of CameraResult
        Every calibrated device (cameras and projector).
    stereo : sequence of StereoEntry
        Pairwise extrinsics.
    title : str
        Page title.
    notes : sequence of str
        Extra lines for the page (e.g. the board used).
    sections : sequence of (str, sequence of str)
        Extra sections (heading, preformatted lines), e.g. the model selection and the weaknesses.

    Returns
    -------
    Path
        The HTML page.
    """
    page, folder = report_paths(calibration_path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(
            f"calibration report: cannot create {folder} ({exc.strerror}); check permissions"
        ) from exc
    parts = [
        f"<h1>{html.escape(title)}</h1>",
        f"<p>calibration file: {html.escape(str(calibration_path))}</p>",
    ]
    parts += [f"<p>{html.escape(n)}</p>" for n in notes]
    for heading, lines in sections:
        if lines:
            body = html.escape("\n".join(lines))
            parts.append(f"<h2>{html.escape(heading)}</h2><pre>{body}</pre>")

    def figure(name: str, img: U8) -> str:
        data = _png(img)
        _write_whole(folder / name, data)
        return f'<img alt="{name}" src="data:image/png;base64,{base64.b64encode(data).decode()}"><br>'

    for res in devices:
        cam = res.camera
        parts.append(f"<h2>{html.escape(cam.name)} ({cam.width}x{cam.height})</h2>")
        parts.append(f"<p>RMS {res.rms:.4f} px over {len(res.views)} views.</p>")
        parts += [f'<p class="warn">warning: {html.escape(w)}</p>' for w in res.warnings]
        parts += [f"<p>rejected view #{i}: {html.escape(w)}</p>" for i, w in sorted(res.rejected.items())]
        parts.append(_param_table(res))
        parts.append(figure(f"{cam.name}_residuals.png", residual_plot(res)))
        labels = [f"#{i}" for i in res.views]
        parts.append(
            figure(
                f"{cam.name}_per_view.png",
                bar_plot(list(res.per_view_errors), labels, f"{cam.name}: per-view RMS (px)"),
            )
        )
        parts.append(figure(f"{cam.name}_coverage.png", coverage_plot(res)))
    for entry in stereo:
        st = entry.result
        R = np.array2string(st.R, precision=6, suppress_small=True)
        T = np.array2string(st.T, precision=3, suppress_small=True)
        parts.append(f"<h2>stereo {html.escape(entry.first)} &rarr; {html.escape(entry.second)}</h2>")
        parts.append(
            f"<p>RMS {st.rms:.4f} px, baseline {st.baseline_mm:.3f} mm</p><pre>R =\n{R}\nT (mm) = {T}</pre>"
        )
        vals = [float(v) for row in st.per_view_errors for v in row]
        labels = [f"#{i}{'ab'[k]}" for i in st.views for k in range(2)]
        parts.append(
            figure(
                f"stereo_{entry.first}_{entry.second}_per_view.png",
                bar_plot(vals, labels, f"stereo {entry.first}(a) / {entry.second}(b): per-view RMS"),
            )
        )
    style = (
        "body{font-family:sans-serif} table{border-collapse:collapse} "
        "td,th{border:1px solid #999;padding:2px 6px}"
    )
    doc = (
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
        f"<style>{style} .warn{{color:#b00}}</style></head><body>{''.join(parts)}</body></html>"
    )
    _write_whole(page, doc.encode("utf-8"))
    return page


def _write_whole(path: Path, data: bytes) -> None:
    """Write a report file whole or not at all (a full disk leaves no empty PNG); one OutputError line."""
    try:
        with open(path, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    except OSError as exc:
        with contextlib.suppress(OSError):
            path.unlink(missing_ok=True)
        raise OutputError(f"calibration report: cannot write {path} ({exc.strerror or exc}); check the folder is "
                          "writable and has free space (the calibration file itself was written)") from exc


def write_rig_calibration(out: Path, result: RigCalibration, board: BoardSpec, title: str) -> Path:
    """Write the calibration file of a rig and its report beside it.

    Parameters
    ----------
    out : Path
        Calibration file (OpenCV YAML).
    result : RigCalibration
        The calibration.
    board : BoardSpec
        The board (named on the page).
    title : str
        Page title.

    Returns
    -------
    Path
        The report page.
    """
    from appliance.geometry.calibration_file import Calibration, write_calibration

    write_calibration(out, Calibration(devices=dict(result.devices)))
    notes = [f"board: {board.describe()}"]
    if result.bundle is not None:
        b = result.bundle
        notes.append(f"joint refinement: RMS {b.rms:.4f} px over {len(b.board_poses)} poses, "
                     f"{b.iterations} iterations, {b.dropped_points} outlier points dropped")  # fmt: skip
    sections = [
        ("Distortion models (leave-one-view-out)", result.model_lines()),
        ("Weaknesses and poses to add", result.weakness_lines()),
    ]
    return write_report(out, result.results, result.stereo, title=title, notes=notes, sections=sections)
