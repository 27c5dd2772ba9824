"""``scan3d verify``: scan the known artefact in every configured position and report VDI/VDE 2634-2 figures.

On a virtual rig the artefact is put into the scene at each position; on real hardware the person is asked
to put it there and press Enter. The fits and figures are :mod:`appliance.calibration.verify`'s.
"""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np
import numpy.typing as npt

from appliance.atomic_write import same_file, write_bytes_atomic
from appliance.calibration.verify import (
    VdiReport,
    artefact_scene,
    evaluate_artefact,
    placed,
    write_verify_page,
)
from appliance.config.schema import AppConfig, ArtefactPosition
from appliance.errors import CalibrationError, ConfigError
from appliance.geometry.calibration_file import Calibration

if TYPE_CHECKING:
    from appliance.scan import Scanner

F64 = npt.NDArray[np.float64]


async def scan_positions(
    cfg: AppConfig,
    calibration: Calibration | None = None,
    positions: tuple[ArtefactPosition, ...] | None = None,
    stdin: TextIO | None = None,
) -> list[F64]:
    """Scan the artefact once per position on the configured rig.

    Parameters
    ----------
    cfg : AppConfig
        Configuration (``calibration.artefact``).
    calibration : Calibration, optional
        Calibration to reconstruct with (default: the configured one, or the virtual rig's exact one).
    positions : tuple of ArtefactPosition, optional
        Default ``calibration.artefact.positions``.
    stdin : text stream, optional
        Real rig: where the Enter after placing the artefact is read (default ``sys.stdin``).

    Returns
    -------
    list of ndarray, shape (N, 3), float64
        The points of each scan (world frame, mm).
    """
    art = cfg.calibration.artefact
    todo = positions if positions is not None else art.positions

    def prepare() -> Scanner:  # renders the virtual rig, builds ray tables: not on the event loop
        # the imports too: appliance.scan brings the decoder and its kernels (~150 ms on a first import)
        from appliance.hardware.registry import build_rig
        from appliance.scan import Scanner, load_calibration_for

        rig = build_rig(cfg)
        return Scanner(cfg, rig, calibration if calibration is not None else load_calibration_for(cfg, rig))

    loop = asyncio.get_running_loop()
    scanner = await loop.run_in_executor(None, prepare)
    rig = scanner.rig
    clouds: list[F64] = []
    try:
        for k, pos in enumerate(todo):
            here = placed(art, pos)
            virtual = rig.virtual
            if virtual is not None:
                from appliance.sim.scene import Scene

                def place(virtual: Any = virtual, here: Any = here) -> None:
                    virtual.set_scene(Scene(artefact_scene(here)))
                    virtual.prepare()

                await loop.run_in_executor(None, place)
            else:
                print(f"put the artefact at position {k + 1} of {len(todo)} (offset {tuple(pos.offset_mm)} mm, "
                      f"turned {pos.rotation_deg:+.0f} deg about z), then press Enter")  # fmt: skip
                line = await loop.run_in_executor(None, (stdin or sys.stdin).readline)
                if not line:
                    raise CalibrationError(
                        f"verify: end of input before position {k + 1} of {len(todo)}; nothing was judged"
                    )
            result = await scanner.scan()
            clouds.append(await loop.run_in_executor(None, np.asarray, result.cloud.xyz, np.float64))
    finally:
        await scanner.close()
    return clouds


async def verify_rig(
    cfg: AppConfig, calibration: Calibration | None = None, stdin: TextIO | None = None
) -> VdiReport:
    """Scan the artefact in every configured position and judge the figures against the MPEs.

    Parameters
    ----------
    cfg : AppConfig
        Configuration.
    calibration : Calibration, optional
        Calibration to check (default: the configured one).
    stdin : text stream, optional
        See :func:`scan_positions`.

    Returns
    -------
    VdiReport
    """
    art = cfg.calibration.artefact
    clouds = await scan_positions(cfg, calibration, stdin=stdin)
    loop = asyncio.get_running_loop()
    reports = []
    for k, (pos, xyz) in enumerate(zip(art.positions, clouds, strict=True)):
        try:
            rep = await loop.run_in_executor(
                None, evaluate_artefact, xyz, placed(art, pos), cfg.calibration.tolerances
            )
        except CalibrationError as exc:
            raise CalibrationError(f"verify: position {k + 1} of {len(art.positions)}: {exc}") from exc
        reports.append(rep)
    return VdiReport(list(art.positions), reports, cfg.calibration.tolerances)


def default_report_path(cfg: AppConfig) -> Path:
    """``verify-report.html`` beside the calibration file (or in the working directory without one)."""
    if cfg.calibration_file is not None:
        return cfg.calibration_file.with_name(cfg.calibration_file.stem + ".verify-report.html")
    return Path("verify-report.html")


def _refuse_overwriting_inputs(page: Path, config: Path | None, cfg: AppConfig) -> None:
    """The report page and its JSON must be neither the configuration nor the calibration file."""
    inputs = [("the configuration", p) for p in (config,) if p is not None]
    inputs += [("calibration_file", p) for p in (cfg.calibration_file,) if p is not None]
    for written in (page, page.with_suffix(".json")):
        clash = same_file(written, inputs)
        if clash is not None:
            raise ConfigError(f"verify: --out {page} would write {written}, which is {clash[0]}; choose another "
                              "--out (e.g. verify-report.html)")


async def verify_command(config: Path | None, out: Path | None = None, stdin: TextIO | None = None) -> int:
    """``scan3d verify``: print the VDI/VDE 2634-2 report, write its page and a JSON beside it.

    Parameters
    ----------
    config : Path or None
        Configuration file (None: the built-in virtual-rig defaults).
    out : Path, optional
        Report page (default :func:`default_report_path`); the JSON goes beside it (``.json``).
    stdin : text stream, optional
        See :func:`scan_positions`.

    Returns
    -------
    int
        0 when every figure is within its MPE, 1 otherwise.
    """
    from appliance.config.loader import load_config

    cfg = load_config(config) if config is not None else AppConfig()
    source = (
        str(cfg.calibration_file) if cfg.calibration_file is not None else "the virtual rig's exact calibration"
    )
    page = out if out is not None else default_report_path(cfg)
    await asyncio.to_thread(_refuse_overwriting_inputs, page, config, cfg)  # before the scans
    n = len(cfg.calibration.artefact.positions)
    print(f"verify: scanning the artefact in {n} positions with {source}")
    report = await verify_rig(cfg, stdin=stdin)
    for line in report.lines():
        print(line)
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(
        None, write_verify_page, page, report, "Verification (VDI/VDE 2634-2)", [f"calibration: {source}"]
    )
    text = json.dumps(report.as_dict(), indent=1)
    await loop.run_in_executor(None, write_bytes_atomic, page.with_suffix(".json"), text.encode())
    print(f"wrote {page} and {page.with_suffix('.json')}")
    return 0 if report.passed else 1
