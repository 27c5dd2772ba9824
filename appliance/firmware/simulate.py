"""The trigger controller's firmware logic on a pseudo-terminal, for tests and benches without a board.

:class:`SimulatedController` runs :class:`~appliance.firmware.controller.Controller` (the code the board
runs) in a thread behind ``os.openpty()``; the host opens the slave path like a USB serial port. Hooks
press the button, pause the firmware (a hung board), unplug it (the pty closes: the host sees an I/O
error) and plug it back (a new pty; an optional symlink is re-pointed to it, the way
``/dev/serial/by-id/`` names follow a board). ``scan3d firmware simulate`` calls :func:`main`.
"""

from __future__ import annotations

import argparse
import os
import queue
import select
import signal
import sys
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field
from types import FrameType

from appliance.firmware import protocol as P
from appliance.firmware.controller import DEBOUNCE_US, Channel, Controller, Pins

# Module-level so tests can shorten them.
POLL_S = 0.001  # the main loop's idle wait, like the board's sleep_ms(1)
BUTTON_HOLD_S = 0.06  # how long a simulated press holds the button down


@dataclass
class PulseTrain:
    """One pulse train the simulated pins emitted."""

    t0_us: int
    n: int
    period_us: int
    channels: list[tuple[int, int, int, str]]  # (channel, width_us, delay_us, polarity) of enabled ones
    stopped_us: int | None = None


@dataclass
class SimPins(Pins):
    """Pins that record what they were told to do."""

    clock_us: Callable[[], int]
    trains: list[PulseTrain] = field(default_factory=list)
    leds: tuple[bool, bool, bool] = (False, False, False)

    def start_pulses(self, n: int, period_us: int, channels: list[Channel]) -> int:
        enabled = [(i, c.width_us, c.delay_us, c.polarity) for i, c in enumerate(channels) if c.enabled]
        t0 = self.clock_us()
        self.trains.append(PulseTrain(t0, n, period_us, enabled))
        return t0

    def stop_pulses(self) -> None:
        if self.trains and self.trains[-1].stopped_us is None:
            self.trains[-1].stopped_us = self.clock_us()

    def set_leds(self, ready: bool, busy: bool, fault: bool) -> None:
        self.leds = (ready, busy, fault)


def _real_clock() -> Callable[[], int]:
    start = time.monotonic_ns()
    return lambda: (time.monotonic_ns() - start) // 1000


class SimulatedController:
    """The controller firmware on a pseudo-terminal.

    Parameters
    ----------
    link : str, optional
        A symlink kept pointing at the current pty slave (re-pointed on :meth:`plug`).
    board_id : str
        The id reported in the HELLO reply.
    proto, fw : int, str
        Versions to announce (tests use them to provoke a mismatch).
    clock_us : callable, optional
        Microsecond clock; real monotonic time by default.
    on_line : callable, optional
        Called with ``("rx" | "tx", bytes)`` for every chunk (traffic logging).

    Notes
    -----
    Every public method is thread-safe; the controller itself is only touched by the simulator thread.
    """

    def __init__(
        self,
        link: str | os.PathLike[str] | None = None,
        *,
        board_id: str = "SIM00000001",
        proto: int = P.PROTO_VERSION,
        fw: str = P.FW_VERSION,
        clock_us: Callable[[], int] | None = None,
        on_line: Callable[[str, bytes], None] | None = None,
    ) -> None:
        self.link = os.fspath(link) if link is not None else None
        self.clock_us = clock_us or _real_clock()
        self.pins = SimPins(self.clock_us)
        self.on_line = on_line
        self.controller = Controller(
            self.clock_us, self.pins, self._write, board_id=board_id, proto=proto, fw=fw
        )
        self._master = -1
        self._slave = -1
        self.path = ""
        self._commands: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._stop = False
        self._paused = False
        self._presses: list[tuple[int, bool]] = []  # pending (t_us, pressed) button edges
        self._last_edge_us = -(10**12)
        self._thread: threading.Thread | None = None
        self.rx_bytes = 0
        self.tx_bytes = 0

    # --- lifecycle ---------------------------------------------------------------------------------------

    def start(self) -> str:
        """Open the pty, start the firmware thread; return the slave path (or the link, when given)."""
        if self._thread is None:
            self._open_pty()
            self._thread = threading.Thread(target=self._run, name="sim-trigger-controller", daemon=True)
            self._thread.start()
        return self.link or self.path

    def close(self) -> None:
        """Stop the thread and close the pty (and remove the link); idempotent."""
        self._stop = True
        self._wake()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        self._close_pty()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._wake_r = self._wake_w = -1
        if self.link is not None and os.path.islink(self.link):
            os.unlink(self.link)

    def __enter__(self) -> SimulatedController:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- hooks -------------------------------------------------------------------------------------------

    def press_button(self, hold_s: float | None = None) -> None:
        """Press and release the button (held ``hold_s``, default :data:`BUTTON_HOLD_S`), after others."""
        hold_us = int((BUTTON_HOLD_S if hold_s is None else hold_s) * 1e6)

        def press() -> None:
            # a distinct press: after the previous one is released and settled
            start = max(self.clock_us(), self._last_edge_us + 2 * DEBOUNCE_US)
            self._presses += [(start, True), (start + hold_us, False)]
            self._last_edge_us = start + hold_us
            self._presses.sort()

        self._call(press)

    def bounce(self, edges_us: list[tuple[int, bool]]) -> None:
        """Inject raw button edges at offsets (µs from now), e.g. a bouncing contact."""

        def inject() -> None:
            now = self.clock_us()
            self._presses += [(now + dt, level) for dt, level in edges_us]
            self._presses.sort()
            self._last_edge_us = max(self._last_edge_us, self._presses[-1][0])

        self._call(inject)

    def pause(self) -> None:
        """Freeze the firmware: no reading, writing, heartbeats or pulses reports (a hung board)."""
        self._call(lambda: setattr(self, "_paused", True))

    def resume(self) -> None:
        """Undo :meth:`pause`."""
        self._call(lambda: setattr(self, "_paused", False))

    def unplug(self) -> None:
        """Close the pty and remove the link, as when the USB cable is pulled (the host's next read fails)."""

        def pull() -> None:
            self._close_pty()
            if self.link is not None and os.path.islink(self.link):
                os.unlink(self.link)  # like udev removing /dev/serial/by-id/...

        self._call(pull)

    def send_raw(self, data: bytes) -> None:
        """Write bytes to the host as they are (noise on the line)."""
        self._call(lambda: self._write(data))

    def plug(self) -> str:
        """Open a new pty (a new path, like a re-enumerated USB device) and re-point the link to it."""
        self._call(self._open_pty)
        return self.link or self.path

    # --- the firmware thread ---------------------------------------------------------------------------

    def _call(self, fn: Callable[[], None], timeout_s: float = 5.0) -> None:
        if self._thread is None or not self._thread.is_alive():
            fn()
            return
        done = threading.Event()

        def run() -> None:
            try:
                fn()
            finally:
                done.set()

        self._commands.put(run)
        self._wake()
        if not done.wait(timeout_s):
            raise TimeoutError("trigger controller simulator did not answer")

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass

    def _open_pty(self) -> None:
        self._close_pty()
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing, no newline translation
        os.set_blocking(master, False)
        self._master, self._slave = master, slave  # keeping the slave open: no EIO while no host is there
        self.path = os.ttyname(slave)
        self.controller.reader.reset()
        if self.link is not None:
            tmp = f"{self.link}.{os.getpid()}.tmp"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(self.path, tmp)
            os.replace(tmp, self.link)

    def _close_pty(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    def _write(self, data: bytes) -> None:
        if self._master < 0:
            return
        try:
            os.write(self._master, data)  # non-blocking: drop when the host does not read
            self.tx_bytes += len(data)
            if self.on_line is not None:
                self.on_line("tx", data)
        except OSError:
            pass

    def _run(self) -> None:
        while not self._stop:
            fds = [self._wake_r] if self._paused or self._master < 0 else [self._wake_r, self._master]
            timeout = POLL_S
            if self._paused:
                timeout = 0.1
            try:
                ready, _, _ = select.select(fds, [], [], timeout)
            except (OSError, ValueError):
                ready = []
            if self._wake_r in ready:
                try:
                    os.read(self._wake_r, 4096)
                except OSError:
                    pass
            while True:
                try:
                    self._commands.get_nowait()()
                except queue.Empty:
                    break
            if self._paused or self._stop:
                continue
            if self._master >= 0:  # read before polling, also right after a resume: input first
                try:
                    data = os.read(self._master, 4096)
                except OSError:  # nothing there (non-blocking) or no host
                    data = b""
                if data:
                    self.rx_bytes += len(data)
                    if self.on_line is not None:
                        self.on_line("rx", data)
                    self.controller.feed(data)
            now = self.clock_us()
            while self._presses and self._presses[0][0] <= now:
                t_us, level = self._presses.pop(0)
                self.controller.button(level, t_us)
            self.controller.poll()


def main(argv: list[str] | None = None) -> int:
    """``scan3d firmware simulate``: run the controller on a pty until Ctrl-C; Enter presses the button.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments (``--link PATH``, ``--id ID``, ``--verbose``).

    Returns
    -------
    int
        Exit status (0).
    """
    parser = argparse.ArgumentParser(
        prog="scan3d firmware simulate",
        description="Run the trigger controller firmware on a pseudo-terminal. Enter (or SIGUSR1) presses "
        "the button; Ctrl-C quits. Point trigger.port in the configuration at the printed path.",
    )
    parser.add_argument("--link", help="keep this symlink pointing at the pty (a stable port path)")
    parser.add_argument("--id", default="SIM00000001", help="board id reported to the host")
    parser.add_argument("-v", "--verbose", action="store_true", help="print the serial traffic")
    args = parser.parse_args(argv or [])

    def log(direction: str, data: bytes) -> None:
        arrow = "<-" if direction == "rx" else "->"
        for line in data.splitlines():
            print(f"{arrow} {line.decode('ascii', 'replace')}", file=sys.stderr, flush=True)

    sim = SimulatedController(args.link, board_id=args.id, on_line=log if args.verbose else None)
    path = sim.start()
    print(path, flush=True)
    print(f"trigger controller simulator (protocol {P.PROTO_VERSION}, firmware {P.FW_VERSION}) on {sim.path}"
          + (f" via {sim.link}" if sim.link else "") + "; Enter presses the button, Ctrl-C quits",
          file=sys.stderr, flush=True)

    def on_usr1(signum: int, frame: FrameType | None) -> None:
        sim.press_button()

    previous = signal.signal(signal.SIGUSR1, on_usr1)
    try:
        while True:
            line = sys.stdin.readline()
            if not line:  # stdin closed: keep running until interrupted
                while True:
                    time.sleep(3600)
            sim.press_button()
            print("button pressed", file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGUSR1, previous)
        sim.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
