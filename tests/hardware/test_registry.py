"""The backend registry is one table: every config ``type:`` has one row, and the rig builder, ``scan3d devices``
and ``scan3d grab`` all choose backends through it."""

from __future__ import annotations

import typing
from pathlib import Path

import pytest
from conftest import REPO

from appliance.cli import main
from appliance.config.backends import (
    AravisCameraConfig,
    CameraConfig,
    GpioTriggerConfig,
    ProjectorConfig,
    TriggerConfig,
    UvcCameraConfig,
)
from appliance.config.loader import load_config
from appliance.errors import BackendUnavailableError
from appliance.hardware.registry import BACKENDS, backend, build_rig
from appliance.hardware.sim import SimCamera, SimProjector, SimTrigger

CONFIG = REPO / "config" / "appliance.yaml"


def _config_types(union: object) -> set[str]:
    members = typing.get_args(typing.get_args(union)[0])
    return {typing.get_args(m.model_fields["type"].annotation)[0] for m in members}


@pytest.mark.parametrize(
    ("role", "union"), [("camera", CameraConfig), ("projector", ProjectorConfig), ("trigger", TriggerConfig)]
)
def test_every_config_type_has_exactly_one_row(role: str, union: object) -> None:
    rows = [b.type for b in BACKENDS if b.role == role]
    assert sorted(rows) == sorted(_config_types(union)), (role, rows)


def test_the_default_rig_is_built_from_the_table() -> None:
    rig = build_rig(load_config(CONFIG))
    assert rig.virtual is not None and rig.cameras
    assert all(isinstance(c, SimCamera) for c in rig.cameras.values())
    assert isinstance(rig.projector, SimProjector) and isinstance(rig.trigger, SimTrigger)


def test_a_missing_library_names_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib

    real_import_module = importlib.import_module

    def without_cv2(name: str, package: str | None = None) -> object:
        if name == "appliance.hardware.uvc":
            raise ImportError("No module named 'cv2'")
        return real_import_module(name, package)

    monkeypatch.setattr(importlib, "import_module", without_cv2)
    cfg = UvcCameraConfig(device="/dev/video-none")
    with pytest.raises(BackendUnavailableError, match=r"backend 'uvc' is unavailable.*pip install opencv"):
        backend("camera", cfg).make("cam0", cfg, None)


def test_the_one_line_checks_come_from_the_table(tmp_path: Path) -> None:
    missing = str(tmp_path / "absent")
    uvc = UvcCameraConfig(device=missing)
    assert backend("camera", uvc).probe(uvc) == f"uvc {missing} — absent"
    gpio = GpioTriggerConfig(chip=missing, line=3)
    assert backend("trigger", gpio).probe(gpio) == f"gpio {missing} line 3 — absent"
    by_serial = AravisCameraConfig(serial="ABC123")
    assert backend("camera", by_serial).probe(by_serial) == "aravis ABC123 — by serial: needs --discover"


def test_scan3d_devices_and_grab_on_the_virtual_rig(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert main(["devices", "--config", str(CONFIG)]) == 0
    lines = capsys.readouterr().out.splitlines()
    cfg = load_config(CONFIG)
    assert lines == [f"camera {n}: sim (virtual rig) — ok" for n in cfg.cameras] + ["projector: sim", "trigger: sim"]
    name = next(iter(cfg.cameras))
    assert main(["grab", "--config", str(CONFIG), "--camera", name, "--out", str(tmp_path)]) == 0
    assert capsys.readouterr().out.split() == [str(tmp_path / f"{name}_000.png")]
    assert (tmp_path / f"{name}_000.png").stat().st_size > 1000
