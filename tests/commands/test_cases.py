"""Declarative regression cases on real captures (``tests/cases/*.yaml``, described in its README).

Each case builds its manifests from a folder of ``../shared/data``, runs them through the real ``scan3d
decode`` command (``cli.main``, no ``--config``: the mode and depth range come from the calibration) as one
batch, and checks the figures the case expects: from independent decodes and the data READMEs, or checks
that need no reference (coverage, local plane fits, left-right consistency).
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
import yaml

from appliance import cli
from appliance.patterns.manifest import load_images, read_manifest

REPO = Path(__file__).resolve().parents[2]
CASES_DIR = Path(__file__).resolve().parents[1] / "cases"
DATA = REPO.parent / "shared" / "data"
_TMP = tempfile.TemporaryDirectory(prefix="scan3d-cases-")


def _load_case(name: str) -> dict[str, Any]:
    doc = yaml.safe_load((CASES_DIR / f"{name}.yaml").read_text())
    assert isinstance(doc, dict), f"{name}.yaml must be a mapping"
    return doc


CASE_NAMES = sorted(p.stem for p in CASES_DIR.glob("*.yaml"))


# --------------------------------------------------------------------------------------------------
# Building the manifests
# --------------------------------------------------------------------------------------------------


def _expand_frames(spec: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Frame generators -> manifest frame mappings (without images)."""
    frames: list[dict[str, Any]] = []
    for item in spec:
        ((kind, p),) = item.items()
        p = p or {}
        if kind == "gray":
            for bit in range(int(p["bits"]) - 1, -1, -1):
                base = {"pattern": "gray", "axis": p["axis"], "bit": bit, "stripe": int(p.get("stripe", 1))}
                frames.append({**base, "inverted": False})
                if p.get("inverses", True):
                    frames.append({**base, "inverted": True})
        elif kind == "phase":
            for step in range(int(p["steps"])):
                frames.append({"pattern": "phase", "axis": p["axis"], "period": float(p["period"]), "step": step,
                               "steps": int(p["steps"]), "offset": float(p.get("offset", 0.0))})  # fmt: skip
        elif kind in ("white", "black"):
            frames.append({"pattern": kind})
        else:
            raise AssertionError(f"case frame generator {kind!r}: use gray, phase, white or black")
    return frames


def _build_manifest(name: str, case: dict[str, Any], capture: str, folder: Path) -> Path:
    spec = case["manifest"]
    data = DATA / case["data"]
    frames = _expand_frames(spec["frames"])
    images = {cam: [data / pattern.format(i=i, capture=capture) for i in range(len(frames))]
              for cam, pattern in spec["cameras"].items()}  # fmt: skip
    doc: dict[str, Any] = {"projector": spec["projector"], "cameras": list(spec["cameras"])}
    if "bit_depth" in spec:
        doc["bit_depth"] = int(spec["bit_depth"])
        doc["stacks"] = {}
        for cam, paths in images.items():
            stack = load_images(paths).astype(np.uint16) << int(spec.get("shift", 0))
            np.save(folder / f"{capture or name}_{cam}.npy", stack)
            doc["stacks"][cam] = f"{capture or name}_{cam}.npy"
    else:
        for i, f in enumerate(frames):
            f["images"] = {cam: str(paths[i]) for cam, paths in images.items()}
    doc["frames"] = frames
    path = folder / f"{capture or name}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


# --------------------------------------------------------------------------------------------------
# Running a case through scan3d decode
# --------------------------------------------------------------------------------------------------


@dataclass
class CaseRun:
    """What one case's ``scan3d decode`` produced."""

    case: dict[str, Any]
    rc: int
    stdout: str
    stderr: str
    manifests: dict[str, Path]
    maps: dict[str, Any] = field(default_factory=dict)
    clouds: dict[str, Any] = field(default_factory=dict)
    report: dict[str, Any] | None = None


def _need_data(case: dict[str, Any]) -> None:
    if not (DATA / case["data"]).is_dir():
        pytest.skip(f"test data {DATA / case['data']} is absent (shared data folder not mounted)")


@functools.cache
def run_case(name: str) -> CaseRun:
    from plyfile import PlyData

    case = _load_case(name)
    folder = Path(_TMP.name) / name
    folder.mkdir(parents=True, exist_ok=True)
    captures = [str(c) for c in case.get("captures", [""])]
    manifests = {c: _build_manifest(name, case, c, folder) for c in captures}
    args = ["decode", *[str(p) for p in manifests.values()], "--maps", str(folder / "maps"), "--timings"]
    if case.get("calibration"):
        args += ["--calibration", str(DATA / case["data"] / case["calibration"]), "--out", str(folder / "clouds")]
        if len(captures) == 1:
            args += ["--report", str(folder / "report.json")]
    args += [str(a) for a in case.get("args", [])]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(args)
    run = CaseRun(case, rc, out.getvalue(), err.getvalue(), manifests)
    for capture, path in manifests.items():
        maps_file = folder / "maps" / f"{path.stem}.npz"
        if maps_file.exists():
            run.maps[capture] = dict(np.load(maps_file))
        ply = folder / "clouds" / f"{path.stem}.ply"
        if ply.exists():
            run.clouds[capture] = PlyData.read(str(ply))["vertex"]
    if (folder / "report.json").exists():
        run.report = json.loads((folder / "report.json").read_text())
    return run


# --------------------------------------------------------------------------------------------------
# Checks
# --------------------------------------------------------------------------------------------------


def _plain_gray(stack: npt.NDArray[np.int32], first: int, bits: int) -> npt.NDArray[np.int64]:
    """Independent reference: MSB-first (pattern, inverse) pairs, bit = pattern > inverse, Gray -> binary."""
    gray = np.zeros(stack.shape[1:], np.int64)
    for j in range(bits):
        gray |= (stack[first + 2 * j] > stack[first + 2 * j + 1]).astype(np.int64) << (bits - 1 - j)
    binary = gray.copy()
    for _ in range(bits):
        gray >>= 1
        binary ^= gray
    return binary


def _xyz(v: Any) -> npt.NDArray[np.float64]:
    return np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)


def _calibration_matrix(run: CaseRun, key: str) -> npt.NDArray[np.float64]:
    import cv2

    fs = cv2.FileStorage(str(DATA / run.case["data"] / run.case["calibration"]), cv2.FILE_STORAGE_READ)
    try:
        return np.asarray(fs.getNode(key).mat(), np.float64)
    finally:
        fs.release()


def _plane_rms(v: Any, window: int, stride: int = 3) -> npt.NDArray[np.float64]:
    """RMS distance to the least-squares plane of each fully valid window x window patch (mm)."""
    row, col = np.asarray(v["row"], np.int64), np.asarray(v["col"], np.int64)
    cam = np.asarray(v["camera"]) if "camera" in v.data.dtype.names else np.zeros(len(row), np.int64)
    keep = cam == 0
    row, col, xyz = row[keep], col[keep], _xyz(v)[keep]
    grid = np.full((int(row.max()) + 1, int(col.max()) + 1, 3), np.nan)
    grid[row, col] = xyz
    r = window // 2
    out = []
    for y in range(r, grid.shape[0] - r, stride):
        for x in range(r, grid.shape[1] - r, stride):
            patch = grid[y - r : y + r + 1, x - r : x + r + 1].reshape(-1, 3)
            if np.isnan(patch).any():
                continue
            s = np.linalg.svd(patch - patch.mean(axis=0), compute_uv=False)
            out.append(s[-1] / math.sqrt(len(patch)))
    return np.asarray(out)


def check(run: CaseRun, c: dict[str, Any]) -> list[str]:
    """Evaluate one check on every capture of the run; returns lines describing what was measured."""
    kind = c["kind"]
    lines: list[str] = []
    for capture, maps in run.maps.items():
        tag = capture or "capture"
        if kind == "decoded_fraction":
            frac = float(maps[f"{c['camera']}_mask"].mean())
            lines.append(f"{tag}: {c['camera']} decoded {frac:.2%}")
            assert frac >= c.get("min", 0.0) and frac <= c.get("max", 1.0), lines[-1]
        elif kind == "plain_gray":
            cam = c["camera"]
            s = read_manifest(run.manifests[capture]).load_stack(cam).astype(np.int32)
            g = c["gate"]
            ok = (s[g["white"]] - s[g["black"]]) >= g["min_dn"]
            ax = c["axes"]
            ref = {a: _plain_gray(s, ax[a]["first"], ax[a]["bits"]) for a in ax}
            lev = maps[f"{cam}_levels"]
            mask = maps[f"{cam}_mask"] & ok
            full = mask & (lev[0] == 0) & (lev[1] == 0)
            coarse = mask & ~full
            same = np.ones(int(full.sum()), bool)
            same_c = np.ones(int(coarse.sum()), bool)
            for a, key, li in (("x", "u", 0), ("y", "v", 1)):
                if a not in ref:
                    continue
                val = maps[f"{cam}_{key}"]
                same &= val[full].astype(np.int64) == ref[a][full]
                lc = lev[li][coarse].astype(np.int64)
                same_c &= np.floor((val[coarse] + 0.5) / (1 << lc)).astype(np.int64) == ref[a][coarse] >> lc
            lines.append(f"{tag}: full resolution {full.mean():.1%} of the image, same code {same.mean():.3%}; "
                         f"coarser {coarse.mean():.1%}, same {same_c.mean() if same_c.size else 1.0:.3%}")
            assert full.mean() >= c["min_overlap"] and same.mean() >= c["min_same"], lines[-1]
            assert same_c.size == 0 or same_c.mean() >= c["min_same_coarse"], lines[-1]
        elif kind == "reference_decode":
            import cv2

            cam = c["camera"]
            viz = cv2.imread(str(DATA / run.case["data"] / c["image"].format(capture=capture)))
            assert viz is not None, f"{tag}: reference image {c['image']} unreadable"
            both = maps[f"{cam}_mask"] & (viz[..., 2] == 128)

            def circular(a: Any, b: Any) -> Any:
                d = np.abs(a.astype(np.float64) - b) % 256.0
                return np.minimum(d, 256.0 - d)

            ex = circular(maps[f"{cam}_u"][both], viz[..., 0][both])
            ey = circular(maps[f"{cam}_v"][both], viz[..., 1][both])
            within = float(np.mean((ex <= c["within_px"]) & (ey <= c["within_px"])))
            lines.append(f"{tag}: both decoded {both.mean():.1%}, within {c['within_px']} px {within:.2%}, "
                         f"median |dx| {np.median(ex):.2f} |dy| {np.median(ey):.2f} px")  # fmt: skip
            assert both.mean() >= c["min_both"] and within >= c["min_within"], lines[-1]
            assert np.median(ex) <= c["max_median_px"] and np.median(ey) <= c["max_median_px"], lines[-1]
        elif kind == "same_decode_as":
            other = run_case(c["case"])
            ref = other.maps[c["capture"]]
            cam = c["camera"]
            m0, m1 = ref[f"{cam}_mask"], maps[f"{cam}_mask"]
            both = m0 & m1
            same = (ref[f"{cam}_u"][both] == maps[f"{cam}_u"][both]) & (ref[f"{cam}_v"][both] == maps[f"{cam}_v"][both])
            lines.append(f"{tag}: decoded {m1.mean():.2%} vs {m0.mean():.2%} in {c['case']}, "
                         f"same codes {same.mean():.3%}")
            assert abs(m1.mean() - m0.mean()) <= c["max_fraction_diff"] and same.mean() >= c["min_same"], lines[-1]
        elif kind in ("points", "coverage", "depth_percentiles", "plane_fit_rms", "left_right"):
            lines += _cloud_check(run, capture, c)
        else:
            raise AssertionError(f"unknown check kind {kind!r}")
    return lines


def _cloud_check(run: CaseRun, capture: str, c: dict[str, Any]) -> list[str]:
    kind = c["kind"]
    tag = capture or "capture"
    v = run.clouds.get(capture)
    assert v is not None, f"{tag}: no cloud was written"
    if kind == "points":
        assert len(v) >= c["min"], f"{tag}: {len(v)} points"
        return [f"{tag}: {len(v)} points"]
    if kind == "coverage":
        cams = list(run.case["manifest"]["cameras"])
        idx = cams.index(c["camera"])
        ncam = np.asarray(v["camera"]) if "camera" in v.data.dtype.names else np.zeros(len(v), np.int64)
        share = float(np.sum(ncam == idx)) / float(run.maps[capture][f"{c['camera']}_mask"].sum())
        line = f"{tag}: points per decoded pixel of {c['camera']} {share:.1%}"
        assert share >= c["min"], line
        return [line]
    if kind == "depth_percentiles":
        xyz = _xyz(v)
        if "rotation" in c:
            xyz = xyz @ _calibration_matrix(run, c["rotation"]).T
        got = np.percentile(xyz[:, 2], c["percentiles"])
        line = f"{tag}: depth {c['percentiles']} % = {np.round(got, 1).tolist()} mm (expected {c['expected_mm']})"
        assert np.all(np.abs(got - np.asarray(c["expected_mm"], float)) <= c["tol_mm"]), line
        return [line]
    if kind == "plane_fit_rms":
        rms = _plane_rms(v, int(c["window"]))
        med = float(np.median(rms))
        line = f"{tag}: local {c['window']}x{c['window']} plane-fit RMS median {med:.3f} mm over {rms.size} patches"
        assert rms.size > 1000, line
        if "median_mm" in c:
            assert abs(med - c["median_mm"]) <= c["tol_mm"], line
        if "max_median_mm" in c:
            assert med <= c["max_median_mm"], line
        return [line]
    # left_right: each point, seen again by the other camera, lands where that camera decoded the same code
    from appliance.geometry.calibration_file import read_calibration

    calib = read_calibration(DATA / run.case["data"] / run.case["calibration"])
    maps = run.maps[capture]
    other = calib.devices[c["other"]]
    px, _ = other.project(_xyz(v))
    x0, y0 = np.floor(px[:, 0]).astype(np.int64), np.floor(px[:, 1]).astype(np.int64)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < other.width) & (y0 + 1 < other.height)
    u_ref = maps[f"{c['camera']}_u"][np.asarray(v["row"])[inside], np.asarray(v["col"])[inside]]
    uo = maps[f"{c['other']}_u"]
    x0, y0 = x0[inside], y0[inside]
    fx, fy = px[inside, 0] - x0, px[inside, 1] - y0
    u_other = ((1 - fy) * ((1 - fx) * uo[y0, x0] + fx * uo[y0, x0 + 1])
               + fy * ((1 - fx) * uo[y0 + 1, x0] + fx * uo[y0 + 1, x0 + 1]))  # bilinear; NaN next to a hole
    du = np.abs(u_ref - u_other)
    seen = np.isfinite(du)
    share = float(np.mean(du[seen] <= c["max_du_px"]))
    line = (f"{tag}: {inside.mean():.1%} of the points inside {c['other']}, {seen.mean():.1%} on its decoded "
            f"pixels, code within {c['max_du_px']} px there for {share:.2%} (median {np.median(du[seen]):.3f} px)")
    assert inside.mean() > 0.95 and seen.mean() > 0.95 and share >= c["min_share"], line
    return [line]


# --------------------------------------------------------------------------------------------------
# Tests
# --------------------------------------------------------------------------------------------------


def _check_params() -> list[Any]:
    params = []
    for name in CASE_NAMES:
        for i, c in enumerate(_load_case(name).get("checks", [])):
            marks = [pytest.mark.xfail(reason=c["xfail"], strict=True)] if "xfail" in c else []
            params.append(pytest.param(name, i, id=f"{name}-{i}-{c['kind']}", marks=marks))
    return params


@pytest.mark.parametrize("name", CASE_NAMES)
def test_case_decodes_cleanly(name: str) -> None:
    """The command succeeds without a config, one timing line per capture and a summary, no traceback."""
    case = _load_case(name)
    _need_data(case)
    run = run_case(name)
    assert run.rc == 0, run.stderr
    assert "Traceback" not in run.stderr
    timing = [json.loads(x) for x in run.stdout.splitlines() if x.startswith("{")]
    per_capture, summary = timing[:-1], timing[-1]
    assert [t["capture"] for t in per_capture] == [p.stem for p in run.manifests.values()]
    parts = ("load_ms", "setup_ms", "decode_ms", "triangulate_ms", "filter_ms", "cloud_ms", "write_ms")
    assert all(set(t) >= {*parts, "total_ms"} for t in per_capture)
    for t in per_capture:  # the parts are the whole (each rounded to a microsecond)
        assert min(t[k] for k in parts) >= 0.0 and abs(sum(t[k] for k in parts) - t["total_ms"]) < 0.02, t
    assert summary["summary"] and summary["captures"] == len(run.manifests) and summary["failed"] == 0
    assert set(run.maps) == set(run.manifests)
    if case.get("calibration"):
        assert set(run.clouds) == set(run.manifests)
        if run.report is not None:  # a single capture also wrote its sidecar
            (capture,) = run.manifests
            assert run.report["counts"]["points"] == len(run.clouds[capture])
            assert run.report["extra"]["mode"] in ("projector", "stereo", "both")
    print("\n".join(x for x in run.stdout.splitlines() if not x.startswith("{")))


@pytest.mark.parametrize(("name", "index"), _check_params())
def test_case_check(name: str, index: int) -> None:
    case = _load_case(name)
    _need_data(case)
    run = run_case(name)
    assert run.rc == 0, run.stderr
    lines = check(run, case["checks"][index])
    print(f"{name}: " + "; ".join(lines))
