"""Calibration health in every reconstruction: offline (``scan3d decode --report``) and in the service.

Both projector axes are coded, so every camera-projector point is overdetermined: the decoded (u, v) must lie
on the projector's epipolar line of its camera pixel. With the virtual rig's exact calibration that residual
is code noise (``ok`` scan after scan); with the projector turned by 0.1 degree or moved by 0.5 mm across the
baseline it is not (``bad`` beyond the tolerance, ``drifting`` against the trend of earlier scans).
A move *along* the baseline is invisible to any epipolar residual (it only rescales the scene): that is
what ``scan3d verify``'s ball bar is for.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
from pathlib import Path
from typing import Any

import e2e_helpers as e2e
import numpy as np
import pytest
import yaml

from appliance import cli
from appliance.config import parse_config
from appliance.geometry.calibration_file import Calibration, write_calibration
from appliance.geometry.camera import CameraModel
from appliance.patterns.from_config import build_sequence
from appliance.patterns.manifest import write_manifest
from appliance.scan import virtual_calibration
from appliance.service import daemon as D
from appliance.service.client import request
from appliance.service.state import State
from appliance.sim.rig import VirtualRig

RIG: dict[str, Any] = {
    "projector": {"width": 640, "height": 400, "focal_px": 900, "principal_px": [320, 380],
                  "position_mm": [175, 0, 0], "look_at_mm": [0, 40, 580]},
    "cameras": {"cam0": {"width": 480, "height": 384, "focal_px": 700, "position_mm": [0, 0, 0],
                         "look_at_mm": [0, 0, 580]}},
}  # fmt: skip
SEQUENCE = {"kind": "gray_phase", "axes": "xy", "periods_px": [16]}


def _turned(p: CameraModel, deg: float) -> CameraModel:
    """The projector turned by ``deg`` about its own x axis (rows move: across the horizontal baseline)."""
    a = np.radians(deg)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    return CameraModel(p.name, p.K, p.dist, p.width, p.height, rx @ p.R, rx @ p.T, p.rms)


def _moved(p: CameraModel, mm: float) -> CameraModel:
    """The projector moved by ``mm`` along its own y axis (across the baseline)."""
    return CameraModel(p.name, p.K, p.dist, p.width, p.height, p.R, p.T + np.array([0.0, mm, 0.0]), p.rms)


@pytest.fixture(scope="module")
def rig_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A recorded capture of the rig and calibration files: exact, projector turned, projector moved."""
    folder = tmp_path_factory.mktemp("health")
    cfg = parse_config(yaml.safe_dump({"sequence": SEQUENCE, "virtual_rig": RIG}), "rig.yaml")
    rig = VirtualRig(cfg.virtual_rig)
    seq = build_sequence(cfg.sequence, rig.projector.width, rig.projector.height)
    files: dict[str, Path] = {}
    for k in range(3):
        np.save(folder / f"s{k}.npy", rig.render(seq, "cam0", seed=20 + k))
        files[f"scan{k}"] = write_manifest(folder / f"scan{k}.yaml", seq, ["cam0"], stacks={"cam0": f"s{k}.npy"})
    exact = virtual_calibration(rig)
    cam, proj = exact.devices["cam0"], exact.devices["projector"]
    for name, p in {"exact": proj, "turned": _turned(proj, 0.1), "moved": _moved(proj, 0.5)}.items():
        files[name] = folder / f"{name}.yaml"
        write_calibration(files[name], Calibration({"cam0": cam, "projector": p}))
    return files


def _decode_report(manifest: Path, calibration: Path, report: Path) -> tuple[dict[str, Any], str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        rc = cli.main(["decode", str(manifest), "--calibration", str(calibration), "--report", str(report)])
    assert rc == 0, out.getvalue()
    return json.loads(report.read_text())["calibration_health"], out.getvalue()


@pytest.mark.parametrize("calibration", ["exact", "turned", "moved"])
def test_decode_report_carries_calibration_health(rig_files: dict[str, Path], tmp_path: Path,
                                                  calibration: str) -> None:  # fmt: skip
    health, printed = _decode_report(rig_files["scan0"], rig_files[calibration], tmp_path / "r.json")
    (check,) = health["checks"]
    assert check["kind"].startswith("ray_ray") and check["devices"] == "cam0/projector"
    assert check["n_samples"] > 1000 and check["reference_px"] > 0 and check["limit_px"] > check["reference_px"]
    assert f"calibration health: {health['status']}" in printed
    if calibration == "exact":
        assert health["status"] == "ok", health
        assert check["residual_px"] < 0.5 * check["limit_px"]
    else:
        assert health["status"] == "bad", health
        assert check["residual_px"] > check["limit_px"]
        assert "limit" in health["reason"]


def _config(tmp: Path, calibration: Path | None) -> Path:
    top: dict[str, Any] = {"sequence": SEQUENCE}
    if calibration is not None:
        top["calibration_file"] = str(calibration)
    path = e2e.write_config(tmp, mdns=None, **top)
    doc = yaml.safe_load(path.read_text())
    doc["virtual_rig"] = RIG
    doc["reconstruction"] = {"min_depth_mm": 300, "max_depth_mm": 1200}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _status(svc: D.Service) -> dict[str, Any]:
    reply = request(svc.socket_path, {"cmd": "status"}, 30)
    return reply["status"] if "status" in reply else reply  # type: ignore[no-any-return]


@pytest.mark.slow
def test_service_reports_health_in_sidecar_status_and_txt(rig_files: dict[str, Path], tmp_path: Path) -> None:
    """Exact calibration: ok on every scan. Then a reload to a projector moved by 0.5 mm: not ok at once."""
    config = _config(tmp_path, None)
    seen: dict[str, Any] = {}

    async def body(svc: D.Service) -> None:
        for _ in range(6):  # ok every time, and a history for the trend
            scan = await e2e.scan_once(svc)
            assert scan["calibration_health"]["status"] == "ok", scan["calibration_health"]
        sidecar = next(Path(p) for p in scan["files"] if p.endswith(".json"))
        seen["sidecar"] = json.loads(sidecar.read_text())["calibration_health"]
        seen["status_ok"] = await asyncio.to_thread(_status, svc)
        seen["txt_ok"] = svc.publisher.txt_record()
        doc = yaml.safe_load(config.read_text())
        doc["calibration_file"] = str(rig_files["moved"])
        config.write_text(yaml.safe_dump(doc, sort_keys=False))
        reply = await asyncio.to_thread(request, svc.socket_path, {"cmd": "reload"}, 60)
        assert reply.get("ok"), reply
        await e2e.await_for(lambda: svc.board.state == State.IDLE, 60)
        seen["after"] = [(await e2e.scan_once(svc))["calibration_health"]["status"] for _ in range(3)]
        seen["status_bad"] = await asyncio.to_thread(_status, svc)

    rc, _svc = e2e.run_in_process(config, body)
    assert rc == 0
    assert seen["sidecar"]["status"] == "ok" and seen["sidecar"]["checks"][0]["n_samples"] > 1000
    assert seen["status_ok"]["calibration_health"]["status"] == "ok"
    assert seen["txt_ok"]["calibration"] == "ok"
    assert all(s != "ok" for s in seen["after"]), seen["after"]
    health = seen["status_bad"]["calibration_health"]
    assert health["status"] in ("bad", "drifting") and health["checks"][0]["residual_px"] > 0
    trend = json.loads((tmp_path / "state" / "calibration_health.json").read_text())
    (entries,) = trend["kinds"].values()
    assert len(entries) == 9 and [e["status"] for e in entries[:6]] == ["ok"] * 6
