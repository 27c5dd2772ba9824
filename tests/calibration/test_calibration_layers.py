"""calibration/ keeps numerics, detection and reports: it drives no rig and starts no event loop."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "appliance" / "calibration"
FORBIDDEN = ("appliance.hardware", "appliance.scan", "appliance.service", "appliance.procedures")


def test_calibration_imports_no_hardware_scan_or_procedures() -> None:
    bad = []
    for path in sorted(PACKAGE.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module is not None:
                names = [node.module]
            bad += [f"{path.name}: {n}" for n in names if n.startswith(FORBIDDEN)]
    assert bad == []


def test_calibration_starts_no_event_loop() -> None:
    calls = []
    for path in sorted(PACKAGE.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in ("run", "run_until_complete", "new_event_loop"):
                if (isinstance(node.value, ast.Name) and node.value.id == "asyncio") or node.attr != "run":
                    calls.append(f"{path.name}:{node.lineno}: {node.attr}")
            if isinstance(node, (ast.AsyncFunctionDef, ast.Await)):
                calls.append(f"{path.name}:{node.lineno}: coroutine code")
    assert calls == []
