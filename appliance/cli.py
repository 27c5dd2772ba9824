"""The ``scan3d`` command line: argument parsing only; every command calls one function below it."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from appliance import __version__
from appliance.errors import ApplianceError

DEFAULT_CONFIG_CANDIDATES = (Path("/etc/scan3d/appliance.yaml"), Path("config/appliance.yaml"))


def default_config() -> Path:
    """``$SCAN3D_CONFIG``, else /etc/scan3d/appliance.yaml, else the repository's config/appliance.yaml."""
    env = os.environ.get("SCAN3D_CONFIG")
    if env:
        return Path(env)
    for p in DEFAULT_CONFIG_CANDIDATES:
        if p.exists():
            return p
    return DEFAULT_CONFIG_CANDIDATES[-1]


def _cmd_patterns(a: argparse.Namespace) -> int:
    from appliance.commands import write_patterns

    return write_patterns(a.out, a.config, a.width, a.height)


def _cmd_decode(a: argparse.Namespace) -> int:
    from appliance.commands import decode_manifests

    return decode_manifests(a.manifest, a.calibration, a.out, a.maps, a.timings, a.decode_config, a.mode, a.report)


def _cmd_scan(a: argparse.Namespace) -> int:
    import asyncio

    from appliance.commands import scan_command

    return asyncio.run(scan_command(a.config, a.out, a.count, a.compare))


def _cmd_tune(a: argparse.Namespace) -> int:
    import asyncio

    from appliance.service import client

    # a running service owns the rig: the tune goes through it (its cameras cannot be opened twice)
    if a.socket is not None or (not a.local and client.service_answers(client.socket_for(a.config, None))):
        return client.tune_command(a.config, a.socket, time_budget_ms=a.time_budget_ms, apply=a.apply)

    from appliance.config import load_config
    from appliance.procedures.tune import tune_command

    return asyncio.run(tune_command(load_config(a.config), a.config, a.time_budget_ms, a.apply))


def _cmd_validate(a: argparse.Namespace) -> int:
    from appliance.commands import validate_config

    return validate_config(a.file or default_config())


def _cmd_run(a: argparse.Namespace) -> int:
    from appliance.service.daemon import run_service

    return run_service(a.config, control_socket=a.control_socket, scans=a.scans, stdin_button=a.stdin_button,
                       ground_truth=a.ground_truth)


def _cmd_status(a: argparse.Namespace) -> int:
    from appliance.service.client import status_command

    return status_command(a.config, a.socket, as_json=a.json)


def _cmd_trigger(a: argparse.Namespace) -> int:
    from appliance.service.client import trigger_command

    return trigger_command(a.config, a.socket, wait=a.wait)


def _cmd_fleet(a: argparse.Namespace) -> int:
    from appliance.fleet import fleet_command

    return fleet_command(a.interface, a.timeout, a.json)


def _cmd_devices(a: argparse.Namespace) -> int:
    from appliance.commands import devices_command

    return devices_command(a.config, discover=a.discover)


def _cmd_grab(a: argparse.Namespace) -> int:
    import asyncio

    from appliance.commands import grab_command

    return asyncio.run(grab_command(a.config, a.camera, a.frames, a.out))


def _cmd_calibrate(a: argparse.Namespace) -> int:
    if a.live or a.what is None:
        import asyncio

        from appliance.procedures.live_calibration import calibrate_live

        return asyncio.run(calibrate_live(a.config, poses=a.poses, out=a.out, save_frames=a.save_frames))
    from appliance.calibration import cli as cal

    board = cal.board_from_args(a)
    a.out = a.out or Path("calibration.yaml")
    if a.what == "camera":
        return cal.calibrate_camera_cli([Path(p) for p in a.inputs], board, a.out, a.model)
    return cal.calibrate_projector_cli([Path(p) for p in a.inputs], board, a.out, a.model, a.projector_model)


def _cmd_verify(a: argparse.Namespace) -> int:
    import asyncio

    from appliance.procedures.verify import verify_command

    return asyncio.run(verify_command(a.config, out=a.out))


def _cmd_firmware(a: argparse.Namespace) -> int:
    if a.action == "install":
        from appliance.hardware.firmware_install import install_firmware

        install_firmware(a.port)
        return 0
    from appliance.firmware import simulate

    return simulate.main(a.rest)


def _cmd_simulate_camera(a: argparse.Namespace) -> int:
    from appliance.commands import simulate_camera_command

    return simulate_camera_command(a.address, a.serial, a.camera, a.manifest, a.config, a.packet_loss)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``scan3d``."""
    p = argparse.ArgumentParser(prog="scan3d", description="Structured-light 3D scanner appliance.")
    p.add_argument("--version", action="version", version=f"scan3d {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    def cmd(name: str, fn: Callable[[argparse.Namespace], int], help_: str) -> argparse.ArgumentParser:
        sp = sub.add_parser(name, help=help_, description=help_)
        sp.set_defaults(func=fn)
        return sp

    def config_arg(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--config", type=Path, default=None, help="configuration file (default: %(default)s → "
                        "$SCAN3D_CONFIG, /etc/scan3d/appliance.yaml, config/appliance.yaml)")

    sp = cmd("patterns", _cmd_patterns, "write the projector images of the configured sequence and a manifest")
    sp.add_argument("--out", type=Path, required=True, help="output folder")
    sp.add_argument("--width", type=int, default=None, help="projector width (px); default: from the config")
    sp.add_argument("--height", type=int, default=None, help="projector height (px)")
    config_arg(sp)

    sp = cmd("decode", _cmd_decode, "decode recorded captures (manifests) offline; several are a batch")
    sp.add_argument("manifest", type=Path, nargs="+")
    sp.add_argument("--calibration", type=Path, default=None, help="calibration file (this project's or "
                    "SLMaster's caliInfo.yml); without it, maps only")
    sp.add_argument("--mode", choices=["projector", "stereo", "both"], default=None,
                    help="camera-projector, camera-camera or both (default: from what the calibration holds)")
    sp.add_argument("--out", type=Path, default=None,
                    help="output cloud (.ply), or a folder for <manifest stem>.ply (always a folder for a batch)")
    sp.add_argument("--maps", type=Path, default=None,
                    help="write u, v, mask, quality, levels per camera (.npz; a folder for a batch)")
    sp.add_argument("--report", type=Path, default=None, help="write the capture's JSON sidecar (one capture)")
    sp.add_argument("--timings", action="store_true",
                    help="print one JSON line of stage timings (ms) per capture and a summary line")
    sp.add_argument("--config", dest="decode_config", type=Path, default=None,
                    help="configuration whose reconstruction settings override the defaults (optional)")

    sp = cmd("scan", _cmd_scan, "run one scan on the configured rig and write cloud, sidecar and preview")
    config_arg(sp)
    sp.add_argument("--out", type=Path, default=None, help="output folder (default: output.directory)")
    sp.add_argument("--count", type=int, default=1, help="number of scans")
    sp.add_argument("--no-compare", dest="compare", action="store_false",
                    help="virtual rig: do not compare with ground truth")

    sp = cmd("tune", _cmd_tune, "probe the scene on the configured rig and choose the scan's exposures "
             "(sequence.exposures_us) for a time budget")
    sp.add_argument("--time-budget-ms", type=float, default=2000.0,
                    help="longest expected capture time (ms; default: %(default)s)")
    sp.add_argument("--apply", action="store_true",
                    help="write the choice into the configuration file (validated, atomic; a service reloads it)")
    config_arg(sp)
    where = sp.add_mutually_exclusive_group()
    where.add_argument("--socket", type=Path, default=None,
                       help="tune through the service on this control socket (default: through the service when "
                       "one answers on the config's service.control_socket, else on the rig directly)")
    where.add_argument("--local", action="store_true",
                       help="probe the rig directly, never through a running service")

    sp = cmd("validate-config", _cmd_validate, "check a configuration file and print what is wrong")
    sp.add_argument("file", type=Path, nargs="?", default=None)

    sp = cmd("run", _cmd_run, "run the appliance service (foreground; systemd runs this)")
    config_arg(sp)
    sp.add_argument("--control-socket", type=Path, default=None, help="override service.control_socket")
    sp.add_argument("--scans", type=int, default=None, help="exit after this many scans (testing, demos)")
    sp.add_argument("--stdin-button", action="store_true", help="Enter on standard input presses the button")
    sp.add_argument("--ground-truth", action="store_true",
                    help="virtual rig: log each scan's error against ground truth (a demonstration aid)")

    for name, fn, help_ in (("status", _cmd_status, "show the appliance's state"),
                            ("trigger", _cmd_trigger, "start a scan")):
        sp = cmd(name, fn, help_)
        config_arg(sp)
        sp.add_argument("--socket", type=Path, default=None, help="control socket (default: from the config)")
        if name == "status":
            sp.add_argument("--json", action="store_true", help="machine-readable output")
        else:
            sp.add_argument("--wait", action="store_true", help="wait for the scan to finish")

    sp = cmd("fleet", _cmd_fleet, "list the appliances announcing _scan3d._tcp (mDNS) on one interface")
    sp.add_argument("--interface", default="127.0.0.1",
                    help="IP address of the interface to browse on (default: %(default)s); never all of them")
    sp.add_argument("--timeout", type=float, default=2.0, help="seconds to listen (default: %(default)s)")
    sp.add_argument("--json", action="store_true", help="machine-readable output")

    sp = cmd("devices", _cmd_devices, "list the configured devices and whether they answer")
    config_arg(sp)
    sp.add_argument("--discover", action="store_true",
                    help="also broadcast GigE Vision discovery on every interface (never on by default)")

    sp = cmd("grab", _cmd_grab, "grab software-triggered frames to PNG (focus, exposure)")
    config_arg(sp)
    sp.add_argument("--camera", required=True, help="configured camera name, or aravis:ADDRESS")
    sp.add_argument("--frames", type=int, default=1)
    sp.add_argument("--out", type=Path, required=True)

    sp = cmd("calibrate", _cmd_calibrate, "calibrate cameras / projector (see scan3d calibrate -h)")
    sp.add_argument("what", nargs="?", choices=["camera", "projector"], default=None)
    sp.add_argument("inputs", nargs="*", help="images (camera) or manifests (projector), one per pose")
    sp.add_argument("--live", action="store_true", help="interactive calibration on the configured rig")
    sp.add_argument("--board", choices=["chessboard", "circles", "acircles", "charuco"], default="chessboard")
    sp.add_argument("--cols", type=int, default=9, help="inner corners / circles per row")
    sp.add_argument("--rows", type=int, default=6, help="inner corners / circles per column")
    sp.add_argument("--square-mm", type=float, default=25.0, help="square size or circle pitch (mm)")
    sp.add_argument("--marker-mm", type=float, default=None, help="ChArUco marker size (mm)")
    sp.add_argument("--dictionary", default="DICT_6X6_250", help="ChArUco ArUco dictionary")
    sp.add_argument("--model", default="auto", help="camera distortion model: auto (chosen by "
                    "leave-one-view-out error), standard (k1 k2 p1 p2 k3), simple (k1 k2 p1 p2), rational")
    sp.add_argument("--projector-model", default="auto", help="projector distortion model (as --model)")
    sp.add_argument("--out", type=Path, default=None,
                    help="calibration file to write (default: calibration.yaml; --live: the configured file)")
    sp.add_argument("--poses", type=int, default=None,
                    help="--live: capture this many poses without waiting for Enter (virtual rig, demos)")
    sp.add_argument("--save-frames", type=Path, default=None,
                    help="--live: keep each pose's white frame per camera in this folder (pose_NN_CAMERA.png)")
    config_arg(sp)

    sp = cmd("verify", _cmd_verify, "scan the known artefact in several positions and check the calibration "
             "against VDI/VDE 2634 part 2 (PF, PS, SD, flatness)")
    config_arg(sp)
    sp.add_argument("--out", type=Path, default=None,
                    help="report page to write (default: verify-report.html beside the calibration file)")

    sp = cmd("firmware", _cmd_firmware, "install or simulate the trigger controller firmware")
    sp.add_argument("action", choices=["install", "simulate"])
    sp.add_argument("--port", default="/dev/ttyACM0", help="serial port of the board (install)")
    sp.add_argument("rest", nargs=argparse.REMAINDER, help="arguments for the simulator")

    sp = cmd("simulate-camera", _cmd_simulate_camera, "serve a fake GigE Vision camera on a loopback address")
    sp.add_argument("--address", default="127.0.0.1", help="loopback address to listen on (port 3956)")
    sp.add_argument("--serial", default="SCAN3D-SIM", help="serial number the camera reports")
    sp.add_argument("--camera", default=None, help="which camera of the manifest / virtual rig (default: first)")
    src = sp.add_mutually_exclusive_group()
    src.add_argument("--manifest", type=Path, default=None, help="serve the frames of this sequence manifest")
    src.add_argument("--virtual-rig", action="store_true", help="render the virtual rig's frames (the default)")
    sp.add_argument("--packet-loss", type=float, default=0.0, help="fraction of packets to drop (0..1)")
    config_arg(sp)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``scan3d``; returns the exit status."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if getattr(args, "config", "absent") is None:
        args.config = default_config()
    try:
        return int(args.func(args))
    except ApplianceError as exc:
        print(f"scan3d {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
