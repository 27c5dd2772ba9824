"""``scan3d verify`` after VDI/VDE 2634 part 2 on the virtual rig, and the figures on exact points.

With the rig's exact calibration the figures sit at the noise floor of the scans; with the camera's focal
length 1 % too long every lateral length shrinks by about 1 % and the sphere-spacing error SD fails.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

from appliance.calibration.verify import VdiReport, evaluate_artefact, placed
from appliance.cli import main
from appliance.config.schema import AppConfig, ArtefactConfig, ArtefactPosition, VerifyTolerances
from appliance.geometry.calibration_file import Calibration, write_calibration
from appliance.geometry.camera import CameraModel
from appliance.sim.rig import device_model

TRUTH = AppConfig().virtual_rig
POSITIONS = """
    positions:
      - {offset_mm: [0, 0, 0]}
      - {offset_mm: [-35, -20, -30], rotation_deg: 45}
      - {offset_mm: [35, 20, 30], rotation_deg: -45}
"""


def run_verify(tmp_path: Path, config_text: str) -> tuple[int, str, dict[str, object], str]:
    cfg = tmp_path / "appliance.yaml"
    cfg.write_text(config_text)
    page = tmp_path / "verify.html"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["verify", "--config", str(cfg), "--out", str(page)])
    return rc, buf.getvalue(), json.loads(page.with_suffix(".json").read_text()), page.read_text()


@pytest.mark.slow
def test_exact_calibration_sits_at_the_noise_floor(tmp_path: Path) -> None:
    rc, text, rep, page = run_verify(tmp_path, "calibration:\n  artefact:" + POSITIONS)
    assert rc == 0, text
    fig = rep["figures_mm"]
    assert isinstance(fig, dict)
    # PF is the peak-to-valley of the point noise (about 6 sigma of ~0.08 mm); the rest is far below the MPEs
    assert 0 < fig["PF"] <= 0.6
    assert abs(fig["PS"]) <= 0.04 and abs(fig["SD"]) <= 0.02 and 0 < fig["flatness"] <= 0.08
    positions = rep["positions"]
    assert isinstance(positions, list) and len(positions) == 3
    for pos in positions:
        for s in pos["spheres"]:
            assert s["form_mm"] <= 8 * s["rms_mm"]  # pure noise: no form error beyond it
    assert "position 3 of 3: offset (35.0, 20.0, 30.0) mm, turned -45 deg" in text
    assert "pass: SD sphere-spacing error" in text and text.rstrip().splitlines()[-2] == "PASS"
    assert "<h2>PASS</h2>" in page and page.count("data:image/png;base64") == 4


@pytest.mark.slow
def test_focal_length_one_percent_off_fails_sphere_spacing(tmp_path: Path) -> None:
    cam = device_model("cam0", TRUTH.cameras["cam0"])
    proj = device_model("projector", TRUTH.projector)
    K = cam.K.copy()
    K[0, 0] *= 1.01
    K[1, 1] *= 1.01
    bad = tmp_path / "perturbed.yaml"
    write_calibration(bad, Calibration({"cam0": CameraModel("cam0", K, cam.dist, cam.width, cam.height),
                                        "projector": proj}))  # fmt: skip
    one = "calibration:\n  artefact:\n    positions: [{offset_mm: [-35, -20, -30], rotation_deg: 45}]\n"
    rc, text, rep, page = run_verify(tmp_path, f"calibration_file: {bad}\n" + one)
    assert rc == 1
    fig = rep["figures_mm"]
    assert isinstance(fig, dict)
    # 100 mm ball bar: about 1 % too short
    assert -1.6 < fig["SD"] < -0.8
    assert "FAIL: SD sphere-spacing error" in text and text.rstrip().splitlines()[-2] == "FAIL"
    assert "<h2>FAIL</h2>" in page


def _artefact_points(art: ArtefactConfig, rng: np.random.Generator, bump_mm: float = 0.0) -> np.ndarray:
    pts = []
    for s in art.spheres:
        d = rng.normal(size=(3000, 3))
        d[:, 2] = -np.abs(d[:, 2])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts.append(np.asarray(s.center_mm) + s.diameter_mm / 2 * d)
    assert art.plane is not None
    n = np.asarray(art.plane.normal) / np.linalg.norm(art.plane.normal)
    a = np.cross(n, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    uv = rng.uniform(-90, 90, (20000, 2))
    bump = bump_mm * np.exp(-(uv[:, 0] ** 2 + uv[:, 1] ** 2) / (2 * 20.0**2))
    pts.append(np.asarray(art.plane.point_mm) + uv[:, :1] * a + uv[:, 1:] * b + bump[:, None] * n)
    return np.concatenate(pts)


def test_placed_artefact_keeps_its_shape() -> None:
    art = ArtefactConfig()
    moved = placed(art, ArtefactPosition(offset_mm=(10.0, -5.0, 20.0), rotation_deg=90.0))
    c0, c1 = (np.asarray(s.center_mm) for s in art.spheres)
    m0, m1 = (np.asarray(s.center_mm) for s in moved.spheres)
    np.testing.assert_allclose(np.linalg.norm(m1 - m0), np.linalg.norm(c1 - c0))
    np.testing.assert_allclose(m1 - m0, [0.0, 100.0, 0.0], atol=1e-9)  # the bar now runs along y
    np.testing.assert_allclose((m0 + m1) / 2, (c0 + c1) / 2 + [10.0, -5.0, 20.0], atol=1e-9)
    assert moved.plane is not None and art.plane is not None
    n0, n1 = np.asarray(art.plane.normal), np.asarray(moved.plane.normal)
    assert n1[2] == pytest.approx(n0[2]) and np.hypot(n1[0], n1[1]) == pytest.approx(np.hypot(n0[0], n0[1]))
    assert moved.ball_bar_length_mm == pytest.approx(100.0)


def test_figures_over_positions_on_exact_points() -> None:
    """Exact spheres and plane at two positions, one plane with a 0.2 mm bump: figures are the worst values."""
    art = ArtefactConfig()
    rng = np.random.default_rng(7)
    positions = [ArtefactPosition(), ArtefactPosition(offset_mm=(20.0, 10.0, 30.0), rotation_deg=30.0)]
    tol = VerifyTolerances()
    reports = [evaluate_artefact(_artefact_points(placed(art, p), rng, bump), placed(art, p), tol)
               for p, bump in zip(positions, (0.0, 0.2), strict=True)]  # fmt: skip
    rep = VdiReport(positions, reports, tol)
    fig = rep.figures()
    assert fig["PF"] == pytest.approx(0.0, abs=1e-6)
    assert fig["PS"] == pytest.approx(0.0, abs=1e-6) and fig["SD"] == pytest.approx(0.0, abs=1e-6)
    assert fig["flatness"] == pytest.approx(0.2, abs=0.03)
    names = {c.name: c.passed for c in rep.checks}
    assert names == {"PF probing error form": True, "PS probing error size": True,
                     "SD sphere-spacing error": True, "flatness": False}  # fmt: skip
    assert not rep.passed and rep.lines()[-1] == "FAIL"
    assert json.loads(json.dumps(rep.as_dict()))["passed"] is False
