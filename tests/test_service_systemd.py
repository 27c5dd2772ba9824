"""The systemd unit verifies and its exposure is 'OK'; the installer's plan is complete and idempotent."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "systemd" / "scan3d.service"
ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(
    ANALYZE is None, reason="systemd-analyze not installed (apt package systemd)"
)


def unit_copy(tmp_path: Path) -> Path:
    """The unit with ExecStart pointing at a binary that exists here (verify checks it)."""
    text = UNIT.read_text().replace("/opt/scan3d/venv/bin/scan3d run", f"{sys.executable} -m appliance run")
    path = tmp_path / "scan3d.service"
    path.write_text(text)
    return path


def test_unit_has_what_the_appliance_needs() -> None:
    text = UNIT.read_text()
    keys = dict(re.findall(r"^(\w+)=(.*)$", text, re.M))
    assert keys["Type"] == "notify" and keys["Restart"] == "on-failure" and int(keys["WatchdogSec"]) > 0
    for k in ("StateDirectory", "CacheDirectory", "RuntimeDirectory", "ProtectHome", "PrivateTmp"):
        assert keys[k] in ("scan3d", "yes"), k
    assert keys["ProtectSystem"] == "strict" and keys["NoNewPrivileges"] == "yes"
    allowed = re.findall(r"^DeviceAllow=(\S+)", text, re.M)
    assert sorted(allowed) == sorted(
        ["char-usb_device", "char-video4linux", "char-ttyACM", "char-hidraw", "char-gpiochip"]
    )
    assert keys["DevicePolicy"] == "closed"
    assert "AF_INET" in keys["RestrictAddressFamilies"]  # GigE, mDNS, the share
    assert "NUMBA_CACHE_DIR=/var/cache/scan3d" in keys["Environment"]


@needs_analyze
def test_systemd_analyze_verify(tmp_path: Path) -> None:
    r = subprocess.run(
        [ANALYZE, "verify", str(unit_copy(tmp_path))], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0, r.stderr
    assert "scan3d.service" not in r.stderr, r.stderr  # no warning about the unit itself


@needs_analyze
def test_systemd_analyze_security_is_ok(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    r = subprocess.run(
        [ANALYZE, "security", "--offline=true", str(unit_copy(tmp_path))],
        capture_output=True,
        text=True,
        timeout=60,
    )
    m = re.search(r"Overall exposure level for scan3d\.service: ([0-9.]+) (\w+)", r.stdout)
    assert m is not None, r.stdout + r.stderr
    with capsys.disabled():
        print(f"\nsystemd-analyze security: exposure {m.group(1)} {m.group(2)}")
    assert float(m.group(1)) <= 3.0 and m.group(2) == "OK"


def test_udev_rules_name_the_devices() -> None:
    text = (REPO / "systemd" / "99-scan3d.rules").read_text()
    rules = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    assert any(
        'ATTRS{idVendor}=="0451"' in r and 'ATTRS{idProduct}=="6401"' in r for r in rules
    )  # LightCrafter
    assert any('SUBSYSTEM=="tty"' in r and "scan3d-trigger" in r for r in rules)  # the controller
    for r in rules:  # every rule is KEY op "value" pairs separated by commas
        for part in r.split(", "):
            assert re.fullmatch(r'[A-Z_]+(\{[^}]+\})?(==|!=|=|\+=)"[^"]*"', part.strip()), part


def test_tmpfiles_lines_are_well_formed() -> None:
    for line in (REPO / "systemd" / "scan3d.conf").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            fields = line.split()
            assert fields[0] == "d" and fields[1].startswith("/") and re.fullmatch(r"[0-7]{4}", fields[2]), (
                line
            )


def test_installer_dry_run_plans_everything() -> None:
    r = subprocess.run(
        ["bash", str(REPO / "scripts" / "install"), "--dry-run"], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0, r.stderr
    out = r.stdout
    for needle in (
        "usermod -a -G dialout,plugdev,video,gpio scan3d",
        "/opt/scan3d/venv",
        "/etc/systemd/system/scan3d.service",
        "/etc/udev/rules.d/99-scan3d.rules",
        "/etc/tmpfiles.d/scan3d.conf",
        "/var/lib/scan3d",
        "Next steps",
    ):
        assert needle in out, needle
    assert "appliance.yaml" in out
