"""Board layer of the trigger controller for a Raspberry Pi Pico (RP2040) running MicroPython.

Copied to the board's root folder as ``main.py`` beside ``protocol.py`` and ``controller.py`` (see
``scan3d firmware install``); MicroPython runs it at power-up. Under CPython this module only imports
(``machine``/``rp2`` are absent) so the package and its type checks stay whole; nothing here is run in
tests: the protocol logic it drives is :mod:`appliance.firmware.controller`, tested on a pseudo-terminal.

Pulse timing comes from one PIO state machine per output channel (10 MHz, 0.1 µs steps), started
together by one register write, so it does not depend on the interpreter. The button is read through a
pin interrupt that only records (level, time); debounce happens in the controller. A byte 0x03 (Ctrl-C)
from the host stops the program and returns to the REPL, which is how ``mpremote`` takes over; the host
driver only ever sends printable ASCII.

Wiring (GPIO numbers): button GP2 to ground (pull-up, active low); ch0 GP6 -> camera Line1;
ch1 GP7 -> projector TRIG_IN; lamps GP10 ready, GP11 busy, GP12 fault (the on-board LED mirrors ready).
"""

import sys

try:
    from appliance.firmware import controller as C
    from appliance.firmware import protocol as P
except ImportError:  # on the board
    import controller as C  # type: ignore[import-not-found, no-redef]
    import protocol as P  # type: ignore[import-not-found, no-redef]

try:
    import select
    import time as _time

    import machine  # type: ignore[import-not-found]
    import rp2  # type: ignore[import-not-found]

    time: "Any" = _time  # MicroPython's time (ticks_us, ticks_diff, sleep_ms)

    ON_BOARD = True
except ImportError:
    ON_BOARD = False

TYPE_CHECKING = False
if TYPE_CHECKING:
    from typing import Any

    # Names that rp2.asm_pio provides while it assembles a PIO program.
    pull: Any = None
    mov: Any = None
    jmp: Any = None
    label: Any = None
    irq: Any = None
    rel: Any = None
    x: Any = None
    y: Any = None
    osr: Any = None
    isr: Any = None
    pins: Any = None
    x_dec: Any = None
    y_dec: Any = None
    set: Any = None

BUTTON_PIN = 2
CHANNEL_PINS = (6, 7)
LED_PINS = (10, 11, 12)  # ready, busy, fault
ONBOARD_LED = 25
PIO_FREQ = 10000000  # state machine clock (Hz): 0.1 µs per cycle
CYCLES_PER_US = PIO_FREQ // 1000000
PIO0_CTRL = 0x50200000  # PIO0 CTRL: SM_ENABLE bits 0..3, CLKDIV_RESTART bits 8..11
IO_BANK0 = 0x40014000  # GPIOn_CTRL at IO_BANK0 + 8 n + 4; OUTOVER bits 8..9 (1 = invert)
EDGE_RING = 16  # button edges buffered between two main-loop passes


def _pulse_train() -> None:
    # FIFO, in order: delay cycles, high cycles - 3, pulses - 1, low cycles - 4 (see _words).
    pull()
    mov(x, osr)
    label("delay")
    jmp(x_dec, "delay")
    pull()
    mov(isr, osr)
    pull()
    mov(y, osr)
    pull()
    label("pulse")
    set(pins, 1)
    mov(x, isr)
    label("high")
    jmp(x_dec, "high")
    set(pins, 0)
    mov(x, osr)
    label("low")
    jmp(x_dec, "low")
    jmp(y_dec, "pulse")
    irq(rel(0))
    label("idle")
    jmp("idle")


def _words(n: int, period_us: int, channel: "C.Channel") -> "tuple[int, int, int, int]":
    high = channel.width_us * CYCLES_PER_US
    low = (period_us - channel.width_us) * CYCLES_PER_US
    return channel.delay_us * CYCLES_PER_US, max(high - 3, 0), n - 1, max(low - 4, 0)


class Clock:
    """``ticks_us`` extended to an unbounded count (it wraps every 2**30 µs); call at least every 8 min."""

    def __init__(self) -> None:
        self.last = time.ticks_us()
        self.now = 0

    def __call__(self) -> int:
        raw = time.ticks_us()
        self.now += time.ticks_diff(raw, self.last)
        self.last = raw
        return self.now

    def extend(self, raw: int) -> int:
        """An earlier raw ``ticks_us`` value on the extended scale."""
        return self() + int(time.ticks_diff(raw, time.ticks_us()))


class BoardPins(C.Pins):
    """PIO pulse outputs and lamp pins."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.program = rp2.asm_pio(set_init=rp2.PIO.OUT_LOW)(_pulse_train)
        self.machines: list[Any] = []
        self.leds = [machine.Pin(p, machine.Pin.OUT, value=0) for p in LED_PINS]
        self.onboard = machine.Pin(ONBOARD_LED, machine.Pin.OUT, value=0)
        for pin in CHANNEL_PINS:
            machine.Pin(pin, machine.Pin.OUT, value=0)

    def start_pulses(self, n: int, period_us: int, channels: "list[C.Channel]") -> int:
        self.stop_pulses()
        mask = 0
        for i, channel in enumerate(channels):
            if not channel.enabled or i >= len(CHANNEL_PINS):
                continue
            self._invert(CHANNEL_PINS[i], channel.polarity == "low")
            sm = rp2.StateMachine(i, self.program, freq=PIO_FREQ, set_base=machine.Pin(CHANNEL_PINS[i]))
            for word in _words(n, period_us, channel):
                sm.put(word)
            self.machines.append(sm)
            mask |= 1 << i
        machine.mem32[PIO0_CTRL] = (mask << 8) | mask  # start together, dividers in phase
        return self.clock()

    def stop_pulses(self) -> None:
        for sm in self.machines:
            sm.active(0)
            sm.exec("set(pins, 0)")
        self.machines = []

    def set_leds(self, ready: bool, busy: bool, fault: bool) -> None:
        states = (ready, busy, fault)
        for i in range(len(self.leds)):
            self.leds[i].value(1 if states[i] else 0)
        self.onboard.value(1 if ready else 0)

    def _invert(self, gpio: int, invert: bool) -> None:
        addr = IO_BANK0 + 8 * gpio + 4
        machine.mem32[addr] = (machine.mem32[addr] & ~(3 << 8)) | ((1 if invert else 0) << 8)


class Button:
    """A pin interrupt records (level, raw ticks) in a ring; :meth:`drain` gives them to the controller."""

    def __init__(self, ctl: "C.Controller", clock: Clock) -> None:
        self.ctl = ctl
        self.clock = clock
        self.pin = machine.Pin(BUTTON_PIN, machine.Pin.IN, machine.Pin.PULL_UP)
        self.levels = bytearray(EDGE_RING)
        self.ticks = [0] * EDGE_RING
        self.head = 0
        self.tail = 0
        self.pin.irq(self._irq, machine.Pin.IRQ_FALLING | machine.Pin.IRQ_RISING)

    def _irq(self, pin: "Any") -> None:
        nxt = (self.head + 1) % EDGE_RING
        if nxt != self.tail:  # full: drop the edge, the level is re-read in drain()
            self.levels[self.head] = pin.value()
            self.ticks[self.head] = time.ticks_us()
            self.head = nxt

    def drain(self) -> None:
        while self.tail != self.head:
            i = self.tail
            self.ctl.button(self.levels[i] == 0, self.clock.extend(self.ticks[i]))
            self.tail = (i + 1) % EDGE_RING
        self.ctl.button(self.pin.value() == 0, None)  # catch edges the ring dropped


def _board_id() -> str:
    raw = machine.unique_id()
    return "".join(f"{b:02X}" for b in raw)


def run() -> None:
    """The firmware's main loop (never returns on the board)."""
    clock = Clock()
    pins = BoardPins(clock)
    out = sys.stdout.buffer
    ctl = C.Controller(clock, pins, out.write, board_id=_board_id(), channels=len(CHANNEL_PINS))
    button = Button(ctl, clock)
    poller = select.poll()
    poller.register(sys.stdin, select.POLLIN)
    inp = sys.stdin.buffer
    buf = bytearray(P.MAX_LINE)
    while True:
        got = 0
        while got < len(buf) and poller.poll(0):
            buf[got] = inp.read(1)[0]
            got += 1
        if got:
            ctl.feed(bytes(buf[:got]))
        button.drain()
        ctl.poll()
        if not got:
            time.sleep_ms(1)


if __name__ == "__main__" and ON_BOARD:
    run()
