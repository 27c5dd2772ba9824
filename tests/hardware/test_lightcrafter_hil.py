"""The LightCrafter 4500 backend against a fake DLPC350 behind the real pyusb ``usb.core`` code paths."""

from __future__ import annotations

import asyncio
import errno
import threading
from collections.abc import Iterator

import numpy as np
import numpy.typing as npt
import pydantic
import pytest
import usb.core

from appliance.config.backends import LightCrafter4500Config, VideoOutputConfig
from appliance.config.loader import parse_config
from appliance.errors import BackendUnavailableError, ConfigError, PatternError, ProjectorError
from appliance.fakes.dlpc350 import FakeDLPC350, FakeUsbBackend, FlashCommandError
from appliance.hardware import dlpc350 as proto
from appliance.hardware import lightcrafter4500 as lcm
from appliance.hardware.dlpc350 import Cmd, Led, LutEntry, Trigger
from appliance.patterns import (
    BlackFrame,
    GrayFrame,
    OtherFrame,
    PhaseFrame,
    Sequence,
    WhiteFrame,
    gray_phase_sequence,
    render_frame,
)

pytestmark = pytest.mark.hil



@pytest.fixture(autouse=True)
def _fast(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(lcm, "WAKE_S", 0.0)
    monkeypatch.setattr(lcm, "VALIDATE_POLL_S", 0.0)
    monkeypatch.setattr(lcm, "flip_clock_ns", lcm.flip_clock_ns)  # a VirtualDisplay replaces it; restored after


@pytest.fixture
def fake() -> Iterator[FakeDLPC350]:
    dev = FakeDLPC350(serial="LCR0001")
    yield dev
    # Whatever a test did, nothing may ever have sent a flash command.
    assert dev.flash_violations == []
    assert not any(proto.is_flash_command(e.code) for e in dev.log)


class VirtualDisplay:
    """A fake :class:`~appliance.hardware.display.Screen` on a virtual clock, and what went out on its HDMI link.

    Each flip returns at the next vsync of a display at ``refresh_hz``: the virtual clock (which becomes the
    backend's flip clock) jumps to it, no real time passes. ``scanned[p]`` is the image index (-1 = black) on
    the link from vsync ``p`` to ``p + 1``. A flip whose number is in ``miss_vsync_at`` misses one vsync: the
    previous frame goes out twice.
    """

    def __init__(self, cfg: VideoOutputConfig, size: tuple[int, int] = (8, 8)) -> None:
        self.cfg = cfg
        self.size = size
        self.period_ns = round(1e9 / cfg.refresh_hz)
        self.t0_ns = 10**9
        self.now_ns = self.t0_ns
        self.images: list[npt.NDArray[np.uint8]] = []
        self.back = -1
        self.scanned: list[int] = []
        self.flips = 0
        self.miss_vsync_at: set[int] = set()
        self.threads: set[threading.Thread] = set()
        self.closed = False
        lcm.flip_clock_ns = self.clock_ns

    def clock_ns(self) -> int:
        return self.now_ns

    @property
    def vsync(self) -> int:
        """Index of the vsync at which the last flip returned."""
        return len(self.scanned) - 1

    def prepare(self, images: list[npt.NDArray[np.uint8]]) -> None:
        assert all(img.shape == (self.size[1], self.size[0], 3) and img.dtype == np.uint8 for img in images)
        self.images = list(images)

    def show(self, index: int) -> None:
        assert -1 <= index < len(self.images)
        self.back = index

    def flip(self) -> None:
        self.threads.add(threading.current_thread())
        if self.flips in self.miss_vsync_at:
            self.scanned.append(self.scanned[-1] if self.scanned else -1)
        self.scanned.append(self.back)
        self.now_ns = self.t0_ns + self.vsync * self.period_ns
        self.flips += 1

    def close(self) -> None:
        self.closed = True

    def frame(self, p: int) -> npt.NDArray[np.uint8]:
        """The image on the link from vsync ``p`` to ``p + 1``."""
        index = self.scanned[p]
        return self.images[index] if index >= 0 else np.zeros((self.size[1], self.size[0], 3), np.uint8)


class Displays:
    """A screen factory that makes :class:`VirtualDisplay` objects of one size and keeps them."""

    def __init__(self, size: tuple[int, int] = (8, 8)) -> None:
        self.size = size
        self.made: list[VirtualDisplay] = []

    def __call__(self, cfg: VideoOutputConfig) -> VirtualDisplay:
        self.made.append(VirtualDisplay(cfg, self.size))
        return self.made[-1]


def _lc(fake: FakeDLPC350, displays: Displays | None = None, **cfg: object) -> lcm.LightCrafter4500:
    return lcm.LightCrafter4500(
        LightCrafter4500Config(**cfg),  # type: ignore[arg-type]
        usb_backend=FakeUsbBackend(fake),
        screen_factory=displays if displays is not None else Displays(),
    )


def _pad(hexstr: str) -> bytes:
    return bytes.fromhex(hexstr).ljust(64, b"\x00")


# --- framing (the documented examples) ------------------------------------------------------------------


def test_request_frames_match_the_documented_examples() -> None:
    assert proto.encode_request(0x1A1B, b"\x01", seq=1) == [_pad("40 01 03 00 1B 1A 01")]
    assert proto.encode_request(0x1A0A, read=True, seq=0) == [_pad("C0 00 02 00 0A 1A")]
    # A message longer than one report continues raw in the next reports.
    data = bytes(range(256)) + bytes(range(128))
    reports = proto.encode_request(0x1A34, data, seq=9)
    assert [len(r) for r in reports] == [64] * 7
    assert reports[0][:6] == bytes.fromhex("40 09 82 01 34 1A") and reports[0][6:] == data[:58]
    assert reports[1] == data[58:122]
    request = proto.decode_request(reports)
    assert (request.code, request.data, request.seq) == (0x1A34, data, 9)


def test_lut_word_bit_layout() -> None:
    e = LutEntry(5, 1, Led.GREEN, Trigger.EXTERNAL_NEGATIVE, invert=True, buffer_swap=True)
    assert e.word() == 2 | 5 << 2 | 1 << 8 | 2 << 12 | 1 << 16 | 1 << 18
    assert LutEntry.from_word(e.word()) == e
    assert (
        LutEntry(2, 8, trig_out_prev=True, insert_black=True).word()
        == 3 | 2 << 2 | 8 << 8 | 7 << 12 | 1 << 17 | 1 << 19
    )
    with pytest.raises(ProjectorError, match="pattern = 3 at bit depth 8"):
        LutEntry(3, 8)


def test_status_bytes_decode_into_messages() -> None:
    assert proto.decode_hardware_status(0x01) == []
    assert proto.decode_hardware_status(0xC4) == [
        "internal initialisation failed",
        "DMD reset controller (DRC) error",
        "sequencer abort",
        "sequencer error",
    ]
    assert proto.decode_main_status(0x0A) == ["sequencer running", "external video locked"]
    assert proto.decode_validation(0x00) == []
    assert len(proto.decode_validation(0x1F)) == 5


# --- golden packets -------------------------------------------------------------------------------------


def test_small_sequence_produces_exactly_the_expected_packets(fake: FakeDLPC350) -> None:
    seq = Sequence(16, 4, (WhiteFrame(), BlackFrame(), GrayFrame("x", 0), PhaseFrame("x", 4.0, 0, 3)))
    lc = _lc(fake, Displays((16, 4)), exposure_us=8333, period_us=8333)  # two patterns per 16667 µs video frame

    async def go() -> None:
        await lc.open()
        n_open = len(fake.log)
        await lc.load(seq)
        loaded = fake.log[n_open:]
        writes = [(e.code, e.request.data.hex(" ")) for e in loaded if not e.request.is_read]
        assert writes == [
            (0x1A24, "00"),  # stop
            (0x1A1B, "01"),  # pattern mode
            (0x1A22, "00"),  # video port source
            (0x1A31, "03 00 03 01"),  # 4 entries, no repeat, 4 patterns per TRIG_OUT2, 2 images
            (0x1A29, "8d 20 00 00 8d 20 00 00"),  # 8333 µs exposure and period
            (0x1A23, "00"),  # VSYNC trigger
            (0x1A33, "02"),  # open the pattern LUT mailbox
            (0x1A32, "00"),
            # G0 white (VSYNC, swap), G1 black (insert black); G0 gray (VSYNC, swap), R 8-bit phase (black)
            (0x1A34, "01 71 04 07 71 02 01 71 04 07 78 02"),
            (0x1A33, "00"),
            (0x1A1D, "00 00 00"),
            (0x1A1E, "00 00"),
            (0x1A07, "08"),
            (0x0B01, "97 78 7d"),  # 255 - (104, 135, 130)
            (0x1A1A, "00"),
        ]
        reads = [e.code for e in loaded if e.request.is_read]
        assert reads == [0x1A1A, 0x1A1A]  # busy once, then the result
        # The exact bytes of one packet, and the sequence numbers run on.
        lut = next(e for e in loaded if e.code == Cmd.MAILBOX_DATA)
        seqs = [e.request.seq for e in loaded]
        assert lut.reports == [
            _pad(f"40 {lut.request.seq:02x} 0e 00 34 1a 01 71 04 07 71 02 01 71 04 07 78 02")
        ]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        await lc.close()

    asyncio.run(go())
    img0, img1 = lc.video_frames
    assert np.all(img0[:, :, 1] == 0b01) and not img0[:, :, [0, 2]].any()  # G0 white, G1 black
    gray = render_frame(GrayFrame("x", 0), 16, 4) > 127
    np.testing.assert_array_equal(img1[:, :, 1], gray.astype(np.uint8))
    np.testing.assert_array_equal(img1[:, :, 0], render_frame(PhaseFrame("x", 4.0, 0, 3), 16, 4))


def _unpack(image: np.ndarray, e: LutEntry) -> np.ndarray:
    rgb = {0: 1, 1: 0, 2: 2}
    if e.bit_depth == 8:
        return image[:, :, rgb[e.pattern]]
    plane = (image[:, :, rgb[e.pattern // 8]] >> (e.pattern % 8)) & 1
    return (plane * 255).astype(np.uint8)


def test_full_gray_phase_sequence_loads_validates_and_runs(fake: FakeDLPC350) -> None:
    seq = gray_phase_sequence(912, 1140, "xy", period=16, steps=4)
    lc = _lc(fake, Displays((912, 1140)), exposure_us=8333, period_us=8333)
    loop_thread = threading.current_thread()
    usb_threads: set[threading.Thread] = set()
    receive = fake.receive

    def spy(report: bytes) -> None:
        usb_threads.add(threading.current_thread())
        receive(report)

    fake.receive = spy  # type: ignore[method-assign]

    async def go() -> lcm.LightCrafterStatus:
        await lc.open()
        await lc.load(seq)
        await lc.start()
        status = await lc.status()
        await lc.close()
        return status

    status = asyncio.run(go())
    assert loop_thread not in usb_threads and usb_threads  # USB I/O never on the event loop's thread
    assert fake.validation == 0 and fake.validated
    assert status.problems == [] and "sequencer running" in status.states
    packing = lc.packing
    assert packing is not None and len(packing.entries) == len(seq) == fake.lut_control[0] + 1
    assert fake.lut_entries() == [e.word() for e in packing.entries]
    # Every frame comes back out of its image's bit plane exactly as the renderer draws it.
    for i, frame in enumerate(seq):
        e = packing.entries[i]
        got = _unpack(packing.images[packing.image_of_frame[i]], e)
        want = render_frame(frame, seq.width, seq.height)
        np.testing.assert_array_equal(got, want if e.bit_depth == 8 else np.where(want > 127, 255, 0))
    # At 8333 µs per pattern and 16667 µs per video frame, two patterns share each image.
    assert max(np.bincount(packing.image_of_frame)) == 2


def test_flash_source_programs_the_image_lut(fake: FakeDLPC350) -> None:
    seq = gray_phase_sequence(64, 32, "x", period=8, steps=3)
    lc = _lc(fake, source="flash", exposure_us=8333, period_us=8333, flash_first_image=5)

    async def go() -> None:
        await lc.open()
        await lc.load(seq)
        await lc.start()
        await lc.close()

    asyncio.run(go())
    assert lc.packing is not None
    n_images = len(lc.packing.images)
    assert fake.source == 3 and fake.trigger_mode == 1 and fake.validation == 0
    assert fake.image_lut[:n_images] == list(range(5, 5 + n_images))
    assert all(LutEntry.from_word(w).trigger == Trigger.INTERNAL for w in fake.lut_entries())


def test_intensity_per_pass_dims_the_configured_led_currents_and_never_refuses_the_sequence(
    fake: FakeDLPC350,
) -> None:
    # sequence.intensities on a LightCrafter: between passes the scan writes the LED PWM values (0x0B01, which the
    # evaluation module takes inverted: 255 - x) scaled from the configured led_current; load sets them back
    seq = gray_phase_sequence(64, 32, "x", period=8, steps=3)
    lc = _lc(fake, source="flash", exposure_us=8333, period_us=8333, led_current=(100, 120, 80))
    seen: list[bytes] = []

    async def go() -> None:
        await lc.open()
        await lc.load(seq)
        seen.append(fake.led_current)
        for level in (0.25, 1.0):
            await lc.set_intensity(level)
            seen.append(fake.led_current)
            await lc.start()  # the validated sequence runs at either level
            assert lc.last_status is not None and not lc.last_status.problems
            await lc.stop()
        for bad in (0.0, 1.5, float("nan"), 0.001):
            with pytest.raises(ProjectorError) as err:
                await lc.set_intensity(bad)
            assert "intensity" in str(err.value) and "lightcrafter4500" in str(err.value)
        await lc.close()

    asyncio.run(go())
    assert seen == [bytes([155, 135, 175]), bytes([230, 225, 235]), bytes([155, 135, 175])]  # 255 - (25, 30, 20)
    writes = [e.request.data for e in fake.log if e.code == 0x0B01 and not e.request.is_read]
    assert len(writes) == 3  # load, then one per pass: the refused values sent nothing


# --- errors ---------------------------------------------------------------------------------------------


def test_invalid_exposure_is_refused_before_anything_is_sent(fake: FakeDLPC350) -> None:
    lc = _lc(fake, exposure_us=16500, period_us=16667)

    async def go() -> None:
        await lc.open()
        n = len(fake.log)
        with pytest.raises(ProjectorError, match=r"exposure_us = 16500.*period - 230 µs = 16437 µs") as err:
            await lc.load(Sequence(8, 8, (WhiteFrame(),)))
        assert "nothing was sent" in str(err.value)
        assert len(fake.log) == n
        await lc.close()

    asyncio.run(go())


@pytest.mark.parametrize(
    ("exposure", "period", "frames", "bit", "text"),
    [
        (16500, 16667, (WhiteFrame(),), 4, "under 230 µs"),
        (4000, 4000, (PhaseFrame("x", 4.0, 0, 3),), 0, "exposure or frame period is invalid"),
    ],
)
def test_forced_invalid_timing_is_rejected_by_the_device_with_decoded_bits(
    fake: FakeDLPC350,
    monkeypatch: pytest.MonkeyPatch,
    exposure: int,
    period: int,
    frames: tuple[WhiteFrame | PhaseFrame, ...],
    bit: int,
    text: str,
) -> None:
    monkeypatch.setattr(proto, "check_exposure_period", lambda *a: [])  # force it past the host check
    lc = _lc(fake, exposure_us=exposure, period_us=period)

    async def go() -> None:
        await lc.open()
        with pytest.raises(
            ProjectorError, match=f"rejected the sequence \\(validation 0x{1 << bit:02X}\\).*{text}"
        ):
            await lc.load(Sequence(8, 8, frames))
        with pytest.raises(ProjectorError, match=r"0x1A24 \(sequence start/stop\).*NACK"):
            await lc.command(0x1A24, b"\x02")  # the device will not start an invalid sequence
        with pytest.raises(ProjectorError, match=r"no sequence loaded \(load\(\) not called or it failed\)"):
            await lc.start()  # nor will the backend present its images
        await lc.close()

    asyncio.run(go())
    assert fake.validation == 1 << bit and not fake.validated


def test_nacks_surface_as_errors_naming_the_command(fake: FakeDLPC350) -> None:
    lc = _lc(fake, exposure_us=8333, period_us=8333)

    async def go() -> None:
        await lc.open()
        with pytest.raises(ProjectorError, match=r"refused 0x1A7F \(unknown\) \(NACK\)"):
            await lc.command(0x1A7F, b"\x00")
        with pytest.raises(ProjectorError, match=r"refused 0x1A1B \(display mode\) \(NACK\) with data 01 02"):
            await lc.command(0x1A1B, b"\x01\x02")  # wrong length
        await lc.load(Sequence(8, 8, (WhiteFrame(), BlackFrame())))
        await lc.start()
        with pytest.raises(ProjectorError, match=r"0x1A29 \(exposure and period\) \(NACK\)"):
            await lc.command(0x1A29, proto.exposure_period_data(8333, 8333))  # while running
        await lc.stop()
        await lc.command(0x1A29, proto.exposure_period_data(8333, 8333))  # accepted once stopped
        await lc.close()

    asyncio.run(go())
    assert [e.nack is not None for e in fake.log if e.code == 0x1A7F] == [True]


def test_flash_commands_never_reach_the_wire(fake: FakeDLPC350) -> None:
    lc = _lc(fake)

    async def go() -> None:
        await lc.open()
        n = len(fake.log)
        for code in (0x0030, 0x0028, 0x0025, 0x0B00, 0x0F10):
            with pytest.raises(ProjectorError, match=f"0x{code:04X} belongs to the flash-programming group"):
                await lc.command(code, b"\x01")
        assert len(fake.log) == n
        await lc.close()

    asyncio.run(go())
    for code in proto.COMMANDS:  # nothing in the command table is a flash command
        assert not proto.is_flash_command(code)


def test_the_fake_flags_a_flash_command_as_a_failure() -> None:
    dev = FakeDLPC350()
    with pytest.raises(FlashCommandError, match="0x0030"):
        dev.receive(proto.encode_request(0x0030, b"\x01")[0])
    assert dev.flash_violations == [0x0030]


def test_open_detaches_the_kernel_driver_wakes_and_close_goes_to_standby(fake: FakeDLPC350) -> None:
    fake.standby = True
    lc = _lc(fake)

    async def go() -> None:
        await lc.open()
        assert not fake.kernel_driver[0] and fake.configuration == 1 and not fake.standby
        await lc.open()  # idempotent
        await lc.close()
        await lc.close()

    asyncio.run(go())
    assert fake.standby and fake.sequencer == 0
    assert fake.writes()[-2:] == [(0x1A24, b"\x00"), (0x0200, b"\x01")]
    assert fake.writes()[0] == (0x0200, b"\x00")
    assert not [t for t in threading.enumerate() if t.name.startswith("lcr4500")]


def test_unhealthy_device_is_reported_on_open(fake: FakeDLPC350) -> None:
    fake.hw_status_faults = 0x04
    with pytest.raises(ProjectorError, match="DMD reset controller \\(DRC\\) error"):
        asyncio.run(_lc(fake).open())


def test_units_are_picked_by_serial() -> None:
    a, b = FakeDLPC350(serial="A1", address=3), FakeDLPC350(serial="B2", address=4)
    backend = FakeUsbBackend(a, b)
    assert lcm.find_device("B2", backend).address == 4
    with pytest.raises(ProjectorError, match="2 LightCrafter 4500 units found \\(serials A1, B2\\)"):
        lcm.find_device(None, backend)
    with pytest.raises(ProjectorError, match="usb_serial = 'C3': no such unit"):
        lcm.find_device("C3", backend)
    with pytest.raises(ProjectorError, match="no LightCrafter 4500 \\(USB 0451:6401\\) found"):
        lcm.find_device(None, FakeUsbBackend())


def test_probe_reports_one_line(fake: FakeDLPC350) -> None:
    assert (
        lcm.probe_lightcrafter(FakeUsbBackend())
        == "lightcrafter4500: no LightCrafter 4500 (USB 0451:6401) found"
    )
    line = lcm.probe_lightcrafter(FakeUsbBackend(fake))
    assert "\n" not in line and "serial LCR0001" in line and "healthy" in line
    assert all(e.request.is_read for e in fake.log)  # the probe changes nothing


def test_sequences_the_device_cannot_show_are_refused(fake: FakeDLPC350) -> None:
    lc = _lc(fake, exposure_us=20000, period_us=20000)
    with pytest.raises(ProjectorError, match="period_us = 20000 is longer than video_frame_period_us"):
        lc._plan(Sequence(8, 8, (WhiteFrame(),)))
    with pytest.raises(PatternError, match="cannot be shown"):
        lcm.pack_video_frames(Sequence(8, 8, (WhiteFrame(), OtherFrame("dots"))))
    with pytest.raises(PatternError, match=r"patterns_per_image = 0: must be 1\.\.24"):
        lcm.pack_video_frames(Sequence(8, 8, (WhiteFrame(),)), patterns_per_image=0)


def test_a_device_object_can_be_passed_in_and_reads_use_the_documented_frame(fake: FakeDLPC350) -> None:
    import usb.core

    dev = usb.core.find(idVendor=0x0451, idProduct=0x6401, backend=FakeUsbBackend(fake))
    lc = lcm.LightCrafter4500(LightCrafter4500Config(), device=dev, screen_factory=Displays())

    async def go() -> None:
        await lc.open()
        await lc.close()

    asyncio.run(go())
    hw = next(e for e in fake.log if e.code == Cmd.HW_STATUS)
    assert hw.reports == [_pad(f"C0 {hw.request.seq:02x} 02 00 0A 1A")]
    assert fake.standby


def _send(dev: FakeDLPC350, code: int, data: bytes = b"", read: bool = False) -> proto.Reply:
    for report in proto.encode_request(code, data, read=read, seq=1):
        dev.receive(report)
    reports = [dev.send()]
    return proto.decode_reply([r for r in reports if r is not None])


def _validate(dev: FakeDLPC350) -> int:
    _send(dev, Cmd.LUT_VALIDATE, b"\x00")
    while (status := _send(dev, Cmd.LUT_VALIDATE, read=True).data[0]) & proto.VALIDATION_BUSY:
        pass
    return status


def test_the_fake_validates_lut_consistency_like_the_device() -> None:
    dev = FakeDLPC350()
    white = LutEntry(0, 1, trigger=Trigger.EXTERNAL_POSITIVE, buffer_swap=True, insert_black=True)
    _send(dev, Cmd.DISPLAY_MODE, b"\x01")
    _send(dev, Cmd.LUT_CONTROL, proto.lut_control_data(2, False, 2, 1))  # says 2 entries ...
    _send(dev, Cmd.MAILBOX_CONTROL, b"\x02")
    _send(dev, Cmd.MAILBOX_DATA, proto.encode_lut([white]))  # ... but only 1 is written
    _send(dev, Cmd.MAILBOX_CONTROL, b"\x00")
    assert proto.VALIDATION_ERRORS[1] in proto.decode_validation(_validate(dev))
    assert _send(dev, Cmd.SEQUENCE_CONTROL, b"\x02").nack  # an invalid sequence does not start
    # An externally triggered pattern after one without insert-black: missing post-vector.
    _send(dev, Cmd.LUT_CONTROL, proto.lut_control_data(2, False, 2, 1))
    _send(dev, Cmd.MAILBOX_CONTROL, b"\x02")
    _send(dev, Cmd.MAILBOX_DATA, proto.encode_lut([LutEntry(0, 1, trigger=Trigger.EXTERNAL_POSITIVE), white]))
    _send(dev, Cmd.MAILBOX_CONTROL, b"\x00")
    assert proto.decode_validation(_validate(dev)) == [proto.VALIDATION_ERRORS[3]]
    assert _send(dev, Cmd.MAILBOX_DATA, b"\x00\x00\x00").nack  # mailbox closed
    assert not dev.validated


# --- video source: the packed images on the HDMI input, in step with the sequencer -------------------------


def _video_lc(
    fake: FakeDLPC350, latency: int = 1, size: tuple[int, int] = (64, 32)
) -> tuple[lcm.LightCrafter4500, Displays, Sequence, list[int]]:
    """A backend at one pattern per video frame, its displays, a sequence, and the vsyncs of start packets."""
    displays = Displays(size)
    lc = _lc(fake, displays, exposure_us=16667, period_us=16667, video_latency_frames=latency)
    starts: list[int] = []
    receive = fake.receive

    def spy(report: bytes) -> None:  # the vsync at which the last flip returned when a start packet arrives
        n = len(fake.log)
        receive(report)
        if len(fake.log) > n and fake.log[-1].code == Cmd.SEQUENCE_CONTROL and fake.log[-1].request.data == b"\x02":
            starts.append(displays.made[-1].vsync)

    fake.receive = spy  # type: ignore[method-assign]
    return lc, displays, gray_phase_sequence(64, 32, "x", period=16, steps=3), starts


def _assert_sequencer_sees_the_packed_images(
    display: VirtualDisplay, images: list[npt.NDArray[np.uint8]], start_vsync: int, latency: int
) -> None:
    """The DLPC350 model: started at the vsync after the start packet, it shows at vsync V the frame that
    arrived ``latency`` frames earlier; it must see images 0..n-1 on consecutive vsyncs, then black."""
    n = len(images)
    for j in range(n):
        np.testing.assert_array_equal(display.frame(start_vsync + 1 + j - latency), images[j], err_msg=f"image {j}")
    after = start_vsync + 1 + n - latency
    assert display.scanned[after] == -1  # then black


def test_video_flip_plan_puts_image_j_where_the_sequencer_looks_at_its_vsync_j() -> None:
    for latency in range(5):
        for n in range(1, 6):
            plan = lcm.video_flip_plan(n, latency, sync_flips=3)
            s = plan.start_after_flip
            assert s == 3 + max(latency - 1, 0)
            # flip k is on the link during [V_k, V_k+1); the sequencer starts at V_(s+1), shows frame m - L at V_m
            shown = [plan.images[s + 1 + j - latency] for j in range(n + 1)]
            assert shown == [*range(n), -1]
            assert plan.images[s + 1 - latency + n :] == [-1] * (latency + 1)
            assert plan.in_step_until == max(s + n - latency, s)
            assert plan.images[:3] == [-1, -1, -1]


@pytest.mark.parametrize("latency", [0, 1, 2, 3])
def test_video_source_shows_each_packed_image_on_the_vsync_the_sequencer_expects_it(
    fake: FakeDLPC350, latency: int
) -> None:
    lc, displays, seq, starts = _video_lc(fake, latency)

    async def go() -> None:
        await lc.open()
        await lc.load(seq)
        await lc.start()
        first_run = list(starts)
        await lc.start()  # again: the sequence stops (back to entry 0) and runs again in step
        assert len(starts) == 2 and starts[0] == first_run[0]
        await lc.stop()
        await lc.close()

    asyncio.run(go())
    display = displays.made[0]
    assert lc.packing is not None
    images = lc.packing.images
    n = len(images)
    assert n == len(seq) > 4  # one pattern per video frame
    assert display.images == images  # the very arrays of the packing
    for start_vsync in starts:
        _assert_sequencer_sees_the_packed_images(display, images, start_vsync, latency)
    assert set(display.scanned[starts[1] + 1 + n - latency :]) == {-1}  # black to the end
    # The start packet went out between the right two flips: after the one carrying image L-1 (black for
    # L = 0), before the one carrying image L.
    for start_vsync in starts:
        assert display.scanned[start_vsync] == latency - 1
        assert display.scanned[start_vsync + 1] == (latency if latency < n else -1)
    assert lc.start_flip == lcm.SYNC_FLIPS + max(latency - 1, 0)
    assert lc.start_delay_us == pytest.approx(0, abs=0.01)  # virtual time stands still during the USB call
    assert np.all(np.diff(lc.flip_times_ns) == display.period_ns)
    # Flips and USB share the backend's worker thread; the display was opened black, closed at the end.
    assert display.scanned[0] == -1 and display.closed
    assert all(t.name.startswith("lcr4500") for t in display.threads)
    assert fake.sequencer == 0 and fake.standby
    writes = fake.writes()
    starts_and_stops = [d for c, d in writes if c == Cmd.SEQUENCE_CONTROL]
    assert starts_and_stops.count(b"\x02") == 2


def test_no_hdmi_signal_is_reported_before_any_pattern_is_shown(fake: FakeDLPC350) -> None:
    lc, displays, seq, starts = _video_lc(fake)

    async def go() -> None:
        await lc.open()
        await lc.load(seq)
        try:
            fake.video_locked = False  # cable out, or the wrong display_index
            mark = len(displays.made[0].scanned)
            with pytest.raises(ProjectorError, match=r"no video signal is locked .*video_output.display_index = 1"):
                await lc.start()
            assert set(displays.made[0].scanned[mark:]) <= {-1} and starts == []  # only black, never started
            fake.video_locked = True
            await lc.start()
            assert len(starts) == 1
        finally:
            await lc.close()

    asyncio.run(go())


def test_a_missed_vsync_is_an_error_and_the_next_start_is_in_step(fake: FakeDLPC350) -> None:
    lc, displays, seq, starts = _video_lc(fake)

    async def go() -> None:
        await lc.open()
        await lc.load(seq)
        display = displays.made[0]
        display.miss_vsync_at = {display.flips + lcm.SYNC_FLIPS + 2}  # while image 2 goes out
        with pytest.raises(ProjectorError, match=r"missed vsync: flip 5 came 33333 µs after.*out of step") as err:
            await lc.start()
        assert "Scan again" in str(err.value)
        assert fake.sequencer == 0 and display.scanned[-1] == -1  # stopped, black
        mark = len(display.scanned)
        await lc.start()
        assert len(starts) == 2 and starts[1] >= mark
        _assert_sequencer_sees_the_packed_images(display, display.images, starts[1], 1)
        await lc.close()

    asyncio.run(go())


def test_a_start_command_later_than_half_a_frame_is_an_error(fake: FakeDLPC350) -> None:
    lc, displays, seq, starts = _video_lc(fake)
    receive = fake.receive

    def slow(report: bytes) -> None:
        receive(report)
        if fake.log[-1].code == Cmd.SEQUENCE_CONTROL and fake.log[-1].request.data == b"\x02":
            displays.made[-1].now_ns += displays.made[-1].period_ns * 6 // 10  # 10 ms of USB latency

    fake.receive = slow  # type: ignore[method-assign]

    async def go() -> None:
        await lc.open()
        await lc.load(seq)
        with pytest.raises(ProjectorError, match=r"start command completed 10000 µs after the vsync.*half a frame"):
            await lc.start()
        assert fake.sequencer == 0 and displays.made[0].scanned[-1] == -1
        await lc.close()

    asyncio.run(go())
    assert len(starts) == 1


def test_a_display_that_is_not_the_packed_image_size_is_refused_at_load(fake: FakeDLPC350) -> None:
    lc, displays, seq, _ = _video_lc(fake, size=(912, 1140))

    async def go() -> None:
        await lc.open()
        n = len(fake.log)
        with pytest.raises(
            ProjectorError, match=r"packed images are 64x32 but the display on the HDMI input .* is 912x1140"
        ) as err:
            await lc.load(seq)
        assert "nothing was sent" in str(err.value) and len(fake.log) == n
        with pytest.raises(ProjectorError, match="no sequence loaded"):
            await lc.start()
        await lc.close()

    asyncio.run(go())
    assert displays.made[0].images == []


def test_stop_stops_the_sequencer_and_shows_black(fake: FakeDLPC350) -> None:
    lc, displays, seq, _ = _video_lc(fake)

    async def go() -> None:
        await lc.open()
        await lc.load(seq)
        await lc.start()
        displays.made[0].back = 3  # whatever was drawn last
        await lc.stop()
        assert fake.sequencer == 0 and displays.made[0].scanned[-1] == -1
        await lc.close()

    asyncio.run(go())


def test_the_flash_source_never_makes_a_display(fake: FakeDLPC350) -> None:
    displays = Displays((64, 32))
    seq = gray_phase_sequence(64, 32, "x", period=8, steps=3)
    for factory in (displays, None):  # None: the default (pygame), which must not be needed
        lc = lcm.LightCrafter4500(
            LightCrafter4500Config(source="flash", exposure_us=8333, period_us=8333),
            usb_backend=FakeUsbBackend(fake),
            screen_factory=factory,
        )

        async def go(lc: lcm.LightCrafter4500 = lc) -> None:
            await lc.open()
            await lc.load(seq)
            await lc.start()
            await lc.stop()
            await lc.close()

        asyncio.run(go())
        assert lc.flip_times_ns == [] and fake.source == 3
    assert displays.made == []


def test_a_display_that_fails_to_open_releases_everything(fake: FakeDLPC350) -> None:
    def broken(cfg: VideoOutputConfig) -> VirtualDisplay:
        raise ProjectorError(f"display: display_index = {cfg.display_index}: only 1 display(s) found")

    lc = lcm.LightCrafter4500(LightCrafter4500Config(), usb_backend=FakeUsbBackend(fake), screen_factory=broken)
    with pytest.raises(ProjectorError, match="display_index = 1"):
        asyncio.run(lc.open())
    assert lc._executor is None and lc._link is None
    assert not [t for t in threading.enumerate() if t.name.startswith("lcr4500")]


def test_close_closes_the_display_even_when_the_usb_part_fails(fake: FakeDLPC350) -> None:
    lc, displays, _, _ = _video_lc(fake)

    def unplugged(report: bytes) -> None:
        raise usb.core.USBError("No such device", errno.ENODEV, errno.ENODEV)

    async def go() -> None:
        await lc.open()
        fake.receive = unplugged  # type: ignore[method-assign]
        with pytest.raises(ProjectorError, match="USB error on 0x1A24"):
            await lc.close()
        await lc.close()  # idempotent

    asyncio.run(go())
    assert displays.made[0].closed
    assert not [t for t in threading.enumerate() if t.name.startswith("lcr4500")]


def test_the_video_source_without_pygame_says_what_to_install(
    fake: FakeDLPC350, without_pygame: None
) -> None:
    lc = lcm.LightCrafter4500(LightCrafter4500Config(), usb_backend=FakeUsbBackend(fake))
    with pytest.raises(BackendUnavailableError, match=r"pip install pygame \(or use source: flash\)"):
        asyncio.run(lc.open())
    assert fake.log == []


def test_video_frame_period_must_match_the_display_refresh_rate() -> None:
    with pytest.raises(
        pydantic.ValidationError,
        match=r"video_frame_period_us = 20000 disagrees with video_output.refresh_hz = 60 .* set "
        r"video_frame_period_us to 16667 or refresh_hz to 50",
    ):
        LightCrafter4500Config(video_frame_period_us=20000)
    with pytest.raises(ConfigError, match=r"appliance.yaml:2: projector: .*refresh_hz = 50 \(frames of 20000 µs\)"):
        parse_config(
            "calibration_file: c.yaml\nprojector:\n  type: lightcrafter4500\n  video_output: {refresh_hz: 50}\n",
            "appliance.yaml",
        )
    assert LightCrafter4500Config(video_frame_period_us=20000, video_output={"refresh_hz": 50}).video_output  # type: ignore[arg-type]
    assert LightCrafter4500Config(video_output={"refresh_hz": 59.94})  # type: ignore[arg-type]  # 0.06 % off: fine


@pytest.mark.filterwarnings("ignore:no fast renderer available")
def test_the_pygame_screen_shows_rgb_bit_planes_and_grey_unchanged(monkeypatch: pytest.MonkeyPatch) -> None:
    pygame = pytest.importorskip("pygame")
    from appliance.hardware.display import PygameScreen

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")  # no real display: SDL's off-screen driver
    monkeypatch.delenv("SDL_VIDEO_DOUBLE_BUFFER", raising=False)  # restored after the test
    screen = PygameScreen("dummy", 0, flip_at_scanout=True)
    try:
        width, height = screen.size
        rng = np.random.default_rng(7)
        rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)  # every bit of every channel matters
        grey = rng.integers(0, 256, (height, width), dtype=np.uint8)
        screen.prepare([rgb, grey])
        for index, want in ((0, rgb), (1, np.repeat(grey[:, :, None], 3, axis=2)), (-1, np.zeros_like(rgb))):
            screen.show(index)
            shown = pygame.surfarray.array3d(pygame.display.get_surface()).transpose(1, 0, 2)
            np.testing.assert_array_equal(shown, want)
            screen.flip()
        with pytest.raises(ProjectorError, match=rf"image 0 is 64x32 but the display is {width}x{height}"):
            screen.prepare([np.zeros((32, 64, 3), np.uint8)])
    finally:
        screen.close()
