"""Install the trigger controller firmware on a MicroPython board with ``mpremote``.

The firmware is three plain files shipped inside the package (``appliance/firmware``): ``protocol.py``
and ``controller.py`` (the logic the host tests run on a pseudo-terminal) and ``main.py`` (the RP2040 board
layer, which MicroPython runs at power-up). They are copied to the board's root folder, ``main.py`` last so
a board interrupted half-way never boots a ``main.py`` without its modules, then the board is reset and,
optionally, asked over the protocol what it now runs.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from importlib import resources
from pathlib import Path

from appliance.errors import BackendUnavailableError, TriggerError

FIRMWARE_FILES = ("protocol.py", "controller.py", "main.py")  # copy order: main.py last
MPREMOTE_TIMEOUT_S = 120.0
VERIFY_TIMEOUT_S = 10.0  # the board re-enumerates on USB after its reset


def find_mpremote() -> str:
    """Path of the ``mpremote`` program (on PATH or beside this Python); raise if it is missing."""
    found = shutil.which("mpremote")
    if found:
        return found
    beside = Path(sys.executable).parent / "mpremote"
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    raise BackendUnavailableError(
        "mpremote (MicroPython's remote control tool) is not installed; install it with "
        "`pip install 'mpremote>=1.20'` into the appliance's environment, then run "
        "`scan3d firmware install` again"
    )


def firmware_dir() -> Path:
    """The folder of the firmware files inside the installed package."""
    return Path(str(resources.files("appliance.firmware")))


def install_command(port: str, mpremote: str) -> list[str]:
    """The ``mpremote`` command line that copies the firmware to the board on ``port`` and resets it."""
    folder = firmware_dir()
    cmd = [mpremote, "connect", port]
    for name in FIRMWARE_FILES:
        cmd += ["fs", "cp", str(folder / name), f":{name}", "+"]
    return [*cmd, "reset"]


def install_firmware(port: str, *, verify: bool = True) -> None:
    """Copy the firmware to the MicroPython board on ``port`` and reset it.

    Parameters
    ----------
    port : str
        Serial device of the board (``/dev/ttyACM0``, ``/dev/serial/by-id/usb-MicroPython_...``).
    verify : bool
        After the reset, wait up to :data:`VERIFY_TIMEOUT_S` for the board to answer the protocol's HELLO
        with this package's protocol version.

    Raises
    ------
    BackendUnavailableError
        ``mpremote`` is not installed.
    TriggerError
        The port is absent, ``mpremote`` failed, or the board does not answer as expected afterwards.
    """
    mpremote = find_mpremote()
    if not os.path.exists(port):
        raise TriggerError(f"firmware install: port {port} does not exist; plug the board in (it appears as "
                           "/dev/ttyACM* with MicroPython) or pass --port")
    for name in FIRMWARE_FILES:
        if not (firmware_dir() / name).is_file():
            raise TriggerError(f"firmware install: {firmware_dir() / name} is missing from the package; "
                               "reinstall scan3d")
    try:
        proc = subprocess.run(install_command(port, mpremote), capture_output=True, text=True,
                              timeout=MPREMOTE_TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired:
        raise TriggerError(f"firmware install on {port}: mpremote did not finish within "
                           f"{MPREMOTE_TIMEOUT_S:g} s; unplug and replug the board and try again") from None
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise TriggerError(
            f"firmware install on {port}: mpremote exited with {proc.returncode}: {' / '.join(tail)}; "
            "is it a MicroPython board, and is no other program (the scan3d service) using the port?"
        )
    if verify:
        _verify(port)


def _verify(port: str) -> None:
    from appliance.firmware import protocol as P
    from appliance.hardware.serial import probe_serial

    deadline = time.monotonic() + VERIFY_TIMEOUT_S
    status = "absent"
    while time.monotonic() < deadline:
        status = probe_serial(port)
        if status.startswith("trigger controller:") and f"(protocol {P.PROTO_VERSION})" in status:
            return
        time.sleep(0.5)
    raise TriggerError(f"firmware install on {port}: files copied, but after the reset the board says: "
                       f"{status}")
