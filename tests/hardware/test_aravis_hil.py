"""The aravis camera backend through the real Aravis stack, against fake GigE Vision cameras on loopback.

Everything runs inside a :class:`LoopbackLab`: a private network namespace (when the test may create one)
where 127.0.0.2+ exist and no packet can reach a real network. Cameras are opened by address, except in the
one test of opening by serial (which needs discovery), and that one runs only inside the private namespace.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Coroutine, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from appliance.config.backends import AravisCameraConfig
from appliance.errors import BackendUnavailableError, CameraError

try:
    from appliance.fakes import gige as fake_gige
    from appliance.hardware import aravis as aravis_backend

    aravis_backend.load_aravis()
    _SKIP = ""
except BackendUnavailableError as exc:
    _SKIP = str(exc)

pytestmark = [
    pytest.mark.hil,
    pytest.mark.skipif(bool(_SKIP), reason=f"gi/Aravis 0.8 cannot be imported: {_SKIP}"),
]

FRAME_TIMEOUT_MS = 400.0


@pytest.fixture(scope="module")
def lab() -> Iterator[fake_gige.LoopbackLab]:
    isolate = os.environ.get("SCAN3D_TEST_NO_NETNS") != "1"  # 1: exercise the 127.0.0.1-only fallback
    with fake_gige.LoopbackLab(n_addresses=3, isolate=isolate) as lab:
        yield lab


def addr(lab: fake_gige.LoopbackLab, k: int) -> str:
    """The lab's k-th loopback address (all 127.0.0.1 without a private namespace)."""
    return lab.addresses[k % len(lab.addresses)]


class Processes:
    """Fake cameras and tool processes of one test; all are stopped at teardown."""

    def __init__(self) -> None:
        self.fakes: list[fake_gige.FakeGigECamera] = []
        self.tools: list[subprocess.Popen[bytes]] = []

    def fake(self, *args: Any, **kwargs: Any) -> fake_gige.FakeGigECamera:
        handle = fake_gige.start_fake_camera(*args, **kwargs)
        self.fakes.append(handle)
        return handle

    def tool(self, address: str, *extra: str) -> subprocess.Popen[bytes]:
        exe = shutil.which("arv-fake-gv-camera-0.8")
        if exe is None:
            pytest.fail("arv-fake-gv-camera-0.8 is missing; apt-get install aravis-tools")
        proc = subprocess.Popen(
            [exe, "-i", address, "-s", "TOOLFAKE", *extra],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        self.tools.append(proc)
        return proc

    def stop_all(self) -> None:
        for handle in self.fakes:
            handle.stop()
        for proc in self.tools:
            if proc.poll() is None:
                proc.kill()
            proc.wait(5)


@pytest.fixture
def procs() -> Iterator[Processes]:
    p = Processes()
    try:
        yield p
    finally:
        p.stop_all()


def run(lab: fake_gige.LoopbackLab, scenario: Callable[[], Coroutine[Any, Any, None]]) -> None:
    """Run an async scenario in the lab's namespace (where its fakes and sockets live)."""
    lab.call(asyncio.run, scenario())


def camera(name: str, address: str, **overrides: Any) -> aravis_backend.AravisCamera:
    settings: dict[str, Any] = {
        "address": address,
        "trigger": "Software",
        "exposure_us": 20000.0,
        "frame_timeout_ms": FRAME_TIMEOUT_MS,
        "reconnect_timeout_s": 3.0,
    }
    settings.update(overrides)
    return aravis_backend.AravisCamera(name, AravisCameraConfig(**settings))


def gray_stack(
    n: int = 12, height: int = 480, width: int = 640, dtype: Any = np.uint8, top: int = 255, seed: int = 3
) -> np.ndarray:
    """A Gray-code-like stack (bit planes of the column's Gray code, and inverses), noisy per frame."""
    gray = np.arange(width) ^ (np.arange(width) >> 1)
    rng = np.random.default_rng(seed)
    frames = np.empty((n, height, width), dtype)
    for i in range(n):
        bit = (gray >> (9 - i // 2)) & 1
        if i % 2:
            bit = 1 - bit
        frame = np.broadcast_to(bit * (top - 40) + 20, (height, width))
        frames[i] = frame + rng.integers(0, 20, (height, width))
    return frames


async def capture(
    cam: aravis_backend.AravisCamera,
    n: int,
    shape: tuple[int, int],
    dtype: Any = np.uint8,
    on_frame: Callable[[int, np.ndarray], None] | None = None,
) -> tuple[np.ndarray, list[int]]:
    out = np.zeros((n, *shape), dtype)
    order: list[int] = []

    def record(i: int, frame: np.ndarray) -> None:
        order.append(i)
        if on_frame is not None:
            on_frame(i, frame)

    await cam.arm(n, out, record)
    await cam.wait_frames(n * FRAME_TIMEOUT_MS / 1000 + 5)
    return out, order


# --- Aravis' own fake camera (arv-fake-gv-camera-0.8) --------------------------------------------------


def test_tool_fake_camera_software_trigger(lab: fake_gige.LoopbackLab, procs: Processes) -> None:
    from appliance.hardware.devices_probe import probe_aravis

    async def scenario() -> None:
        procs.tool("127.0.0.1")
        await asyncio.sleep(0.3)
        cam = camera("left", "127.0.0.1")
        try:
            line = await asyncio.to_thread(probe_aravis, "127.0.0.1")
            assert line.startswith("aravis 127.0.0.1: Aravis Fake serial TOOLFAKE,") and "Software" in line
            info = await cam.open()
            assert (info.model, info.serial, info.pixel_format) == ("Aravis Fake", "TOOLFAKE", "Mono8")
            out, order = await capture(cam, 6, (info.height, info.width))
        finally:
            await cam.close()
        assert order == list(range(6))
        # The fake's test image is a diagonal ramp that moves by one pixel per frame.
        assert out.max() > 100
        for i in range(5):
            np.testing.assert_array_equal(out[i + 1][:, :-1], out[i][:, 1:])
        assert cam.stats.frames_ok == 6 and cam.stats.frames_lost == 0

    run(lab, scenario)


def test_tool_fake_camera_packet_loss_fails_cleanly(lab: fake_gige.LoopbackLab, procs: Processes) -> None:
    async def scenario() -> None:
        lossy = procs.tool("127.0.0.1", "-r", "50")  # 5 % of the packets: nearly every frame is hit
        cam = camera("left", "127.0.0.1")
        try:
            info = await cam.open()
            with pytest.raises(aravis_backend.FrameLostError) as err:
                await capture(cam, 8, (info.height, info.width))
            message = str(err.value)
            i = err.value.frame_index
            assert err.value.status in ("MISSING_PACKETS", "TIMEOUT", "NO_FRAME")
            assert "camera 'left'" in message and "127.0.0.1" in message
            assert f"frame {i} of 8" in message and "check" in message
            assert cam.stats.frames_lost >= 1 and cam.stats.scans_failed == 1
            # The same camera without loss: the next acquisition succeeds (the backend reconnects by itself).
            lossy.kill()
            lossy.wait(5)
            procs.tool("127.0.0.1")
            await asyncio.sleep(0.3)
            out, order = await capture(cam, 8, (info.height, info.width))
            assert order == list(range(8)) and out.max() > 100
            assert cam.stats.scans_ok == 1
        finally:
            await cam.close()

    run(lab, scenario)


# --- the Python-hosted fake serving known frames ---------------------------------------------------


@pytest.mark.parametrize(
    ("pixel_format", "dtype", "top"),
    [("Mono8", np.uint8, 255), ("Mono12", np.uint16, 4095), ("Mono16", np.uint16, 65535)],
)
def test_frames_arrive_bit_exact_in_order(
    lab: fake_gige.LoopbackLab, procs: Processes, pixel_format: str, dtype: Any, top: int
) -> None:
    frames = gray_stack(dtype=dtype, top=top)
    address = addr(lab, 0)

    async def scenario() -> None:
        await asyncio.to_thread(procs.fake, address, "PYFAKE1", frames)
        cam = camera("left", address, pixel_format=pixel_format)
        try:
            info = await cam.open()
            assert (info.width, info.height, info.pixel_format) == (640, 480, pixel_format)
            for _ in range(2):  # a second scan starts again at frame 0
                out, order = await capture(cam, len(frames), (480, 640), dtype)
                assert order == list(range(len(frames)))
                await asyncio.to_thread(np.testing.assert_array_equal, out, frames)  # 50+ ms: not on the loop
        finally:
            await cam.close()

    run(lab, scenario)


def test_skipped_frame_names_its_index_and_next_scan_works(
    lab: fake_gige.LoopbackLab, procs: Processes
) -> None:
    frames = gray_stack()
    address = addr(lab, 0)

    async def scenario() -> None:
        fake = await asyncio.to_thread(procs.fake, address, "PYFAKE2", frames, skip_frames=[5])
        cam = camera("left", address)
        try:
            await cam.open()
            with pytest.raises(aravis_backend.FrameLostError) as err:
                await capture(cam, len(frames), (480, 640))
            assert err.value.frame_index == 5 and err.value.status == "NO_FRAME"
            assert "frame 5 of 12" in str(err.value) and address in str(err.value)
            fake.skip_frames([])
            out, _ = await capture(cam, len(frames), (480, 640))
            np.testing.assert_array_equal(out, frames)
            assert cam.stats.scans_failed == 1 and cam.stats.scans_ok == 1
        finally:
            await cam.close()

    run(lab, scenario)


def test_packet_loss_fails_cleanly_and_next_scan_works(lab: fake_gige.LoopbackLab, procs: Processes) -> None:
    frames = gray_stack()
    address = addr(lab, 0)

    async def scenario() -> None:
        fake = await asyncio.to_thread(procs.fake, address, "PYFAKE3", frames, packet_loss=0.05)
        cam = camera("left", address, frame_timeout_ms=1500.0)  # incomplete frames come out late
        try:
            await cam.open()
            with pytest.raises(aravis_backend.FrameLostError) as err:
                await capture(cam, len(frames), (480, 640))
            assert err.value.status in ("MISSING_PACKETS", "TIMEOUT", "NO_FRAME")
            assert f"frame {err.value.frame_index} of 12" in str(err.value)
            assert cam.stats.statuses[err.value.status] >= 1
            fake.set_packet_loss(0.0)
            out, _ = await capture(cam, len(frames), (480, 640))
            np.testing.assert_array_equal(out, frames)
        finally:
            await cam.close()

    run(lab, scenario)


def test_camera_vanishes_mid_scan_then_reconnects(lab: fake_gige.LoopbackLab, procs: Processes) -> None:
    frames = gray_stack()
    address = addr(lab, 1)

    async def scenario() -> None:
        fake = await asyncio.to_thread(procs.fake, address, "PYFAKE4", frames)
        cam = camera("left", address)
        try:
            await cam.open()

            def pull_cable(i: int, _frame: np.ndarray) -> None:
                if i == 4:
                    fake.process.kill()

            with pytest.raises(CameraError) as err:
                await capture(cam, len(frames), (480, 640), on_frame=pull_cable)
            assert isinstance(err.value, aravis_backend.FrameLostError)
            assert err.value.frame_index == 5 and "camera 'left'" in str(err.value)
            assert err.value.status in ("DISCONNECTED", "NO_FRAME")
            await asyncio.to_thread(fake.stop)
            await asyncio.to_thread(procs.fake, address, "PYFAKE4", frames)
            out, order = await capture(cam, len(frames), (480, 640))
            assert order == list(range(len(frames)))
            np.testing.assert_array_equal(out, frames)
            assert cam.stats.reconnects == 1
        finally:
            await cam.close()

    run(lab, scenario)


def test_line1_hardware_trigger_and_lost_frame(lab: fake_gige.LoopbackLab, procs: Processes) -> None:
    frames = gray_stack(n=8, height=240, width=320)
    address = addr(lab, 2)

    async def scenario() -> None:
        fake = await asyncio.to_thread(procs.fake, address, "PYFAKE5", frames, line_rate_hz=40.0)
        cam = camera("left", address, trigger="Line1")
        try:
            await cam.open()
            out, order = await capture(cam, len(frames), (240, 320))
            assert order == list(range(len(frames)))
            np.testing.assert_array_equal(out, frames)
            # A pulse's frame lost whole: the camera's frame ids jump; the backend says which frame.
            fake.skip_frames([3])
            with pytest.raises(aravis_backend.FrameLostError) as err:
                await capture(cam, len(frames), (240, 320))
            assert err.value.frame_index == 3 and err.value.status == "SKIPPED"
            assert "trigger" in str(err.value) or "frame id jumped" in str(err.value)
            # grab() fires a software trigger even on a Line1 camera.
            fake.skip_frames([])
            frame = await cam.grab()
            np.testing.assert_array_equal(frame, frames[0])
        finally:
            await cam.close()

    run(lab, scenario)


def test_unreachable_address_fails_with_a_clear_message(lab: fake_gige.LoopbackLab) -> None:
    async def scenario() -> None:
        cam = camera("right", "127.0.0.9", reconnect_timeout_s=0.0)  # nothing listens there
        try:
            with pytest.raises(CameraError, match=r"camera 'right' \(aravis, 127\.0\.0\.9\): cannot connect"):
                await cam.open()
        finally:
            await cam.close()

    run(lab, scenario)


def test_capture_via_fake_gige_two_cameras() -> None:
    stacks = {
        "left": gray_stack(n=6, height=120, width=160, seed=1),
        "right": gray_stack(n=6, height=100, width=140, seed=2),
    }
    got = _capture_via_fake_gige(stacks)
    assert set(got) == {"left", "right"}
    for name, stack in stacks.items():
        np.testing.assert_array_equal(got[name], stack)


def _spin(seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass


@pytest.mark.parametrize("retries", [None, 0], ids=["default-retries", "no-retries"])
def test_a_camera_opened_beside_a_streaming_camera_gets_its_own_frames(
    lab: fake_gige.LoopbackLab, procs: Processes, monkeypatch: pytest.MonkeyPatch, retries: int | None
) -> None:
    """Regression: where raw sockets are allowed (root, as here) Aravis' packet socket sees every GVSP packet on
    the interface until its port filter is attached. A camera opened while another streamed took some of that
    camera's frames, and their higher frame ids then made it discard its own first frames as late: frame 0
    never arrived in 2 of 4 to 2 of 25 two-camera captures under a CPU hog (0 of 60 with one camera). The
    backend now replaces a new stream that received anything before its first acquisition (0 of 60, 18
    streams replaced), but not always: CI's run of 2026-12-04 replaced three in a row and the fourth, not
    looked at, lost frame 0. Every new stream is now looked at, and after ``FOREIGN_STREAM_RETRIES`` polluted
    ones the next receives through a UDP socket of its own port, which cannot see another camera's packets
    (here 1-3 of the 8 streams are replaced in each of 15 runs). Here one camera streams without pause, two
    processes load the CPU, and the other camera is opened and scanned eight times: every one of its frames
    arrives exact. With no packet-socket retries (``retries`` 0) the first polluted stream is replaced by a
    UDP one at once (when one is polluted: 1-3 of 8 here), which proves that path."""
    _require_isolation(lab)
    busy, quiet = addr(lab, 0), addr(lab, 1)
    stack = gray_stack(n=6, height=100, width=140)
    if retries is not None:
        monkeypatch.setattr(aravis_backend, "FOREIGN_STREAM_RETRIES", retries)
    replaced = own_port = 0

    async def scenario() -> None:
        nonlocal replaced, own_port
        await asyncio.to_thread(procs.fake, busy, "BUSY1", stack)
        await asyncio.to_thread(procs.fake, quiet, "QUIET1", stack)
        streamer = camera("busy", busy, pixel_format="Mono8", frame_timeout_ms=3000.0)
        await streamer.open()
        stop = asyncio.Event()

        async def stream_on() -> int:
            scans = 0
            while not stop.is_set():
                out, _ = await capture(streamer, len(stack), (100, 140))
                np.testing.assert_array_equal(out, stack)
                scans += 1
            return scans

        task = asyncio.create_task(stream_on())
        try:
            for _ in range(8):
                cam = camera("quiet", quiet, pixel_format="Mono8", frame_timeout_ms=3000.0)
                await cam.open()
                try:
                    out, order = await capture(cam, len(stack), (100, 140))
                    assert order == list(range(len(stack)))
                    np.testing.assert_array_equal(out, stack)
                    replaced += cam.stats.foreign_streams
                    own_port += cam.stats.own_port_streams
                finally:
                    await cam.close()
        finally:
            stop.set()
            scans = await task
            await streamer.close()
        assert scans >= 2  # the other camera really streamed meanwhile
        if retries == 0:  # every polluted stream was followed by one of its own port's socket
            assert own_port == replaced

    ctx = multiprocessing.get_context("spawn")
    hogs = [ctx.Process(target=_spin, args=(60.0,), daemon=True) for _ in range(2)]
    for h in hogs:
        h.start()
    try:
        run(lab, scenario)
    finally:
        for h in hogs:
            h.terminate()
            h.join()


SMALL_RIG = """
cameras: {cam0: {type: sim}}
virtual_rig:
  projector: {width: 640, height: 400, focal_px: 800, principal_px: [320, 200], position_mm: [190, 0, 0],
              look_at_mm: [0, 0, 600]}
  cameras:
    cam0: {width: 320, height: 256, focal_px: 520, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}
"""


def test_simulate_camera_command_serves_the_virtual_rig(
    lab: fake_gige.LoopbackLab, tmp_path: Path
) -> None:
    """``scan3d simulate-camera --virtual-rig``: the command hands the tool the rig's frames; Aravis gets them."""
    from appliance.commands import virtual_rig_frames

    config = tmp_path / "rig.yaml"
    config.write_text(SMALL_RIG)
    address = addr(lab, 2)
    expected = virtual_rig_frames(config, "cam0")
    proc = lab.call(
        subprocess.Popen,
        [sys.executable, "-m", "appliance", "simulate-camera", "--virtual-rig", "--config", str(config),
         "--address", address, "--serial", "SIMCMD"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith(f"serving {expected.frame_count} frames of 320x256 uint8"), proc.stderr.read()

        async def scenario() -> None:
            cam = camera("left", address)
            try:
                info = await cam.open()
                assert (info.serial, info.width, info.height) == ("SIMCMD", 320, 256)
                out, order = await capture(cam, 4, (256, 320))
            finally:
                await cam.close()
            assert order == [0, 1, 2, 3]
            for i in range(4):
                np.testing.assert_array_equal(out[i], expected.render(i))

        run(lab, scenario)
    finally:
        proc.kill()
        proc.wait(5)


def test_simulate_camera_bad_input_is_one_line(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "appliance", "simulate-camera", "--manifest", str(tmp_path / "missing.yaml")],
        capture_output=True, text=True, timeout=60, check=False,
    )
    assert out.returncode != 0
    assert out.stderr.startswith("scan3d simulate-camera: ") and out.stderr.count("\n") == 1, out.stderr


def _capture_via_fake_gige(
    frames_per_camera: dict[str, npt.NDArray[Any]],
    base_address: str = "127.0.0.2",
    *,
    frame_timeout_ms: float = 5000.0,
) -> dict[str, npt.NDArray[Any]]:
    """:func:`_capture_once`: every camera's frames through its own fake, at once."""
    return _capture_once(frames_per_camera, base_address, frame_timeout_ms=frame_timeout_ms)


def _capture_once(
    frames_per_camera: dict[str, npt.NDArray[Any]],
    base_address: str,
    *,
    frame_timeout_ms: float,
) -> dict[str, npt.NDArray[Any]]:
    """Send each camera's frames through a fake GigE Vision camera and capture them with the aravis backend.

    The frame timeout is generous (5 s): these tests check what arrives, not how fast; a loaded CI machine
    once took over 2 s for a fake camera's first frame.

    Starts one fake per camera (addresses from ``base_address`` upwards, in a
    :class:`~appliance.fakes.gige.LoopbackLab` private network namespace when possible; otherwise one camera
    after the other on 127.0.0.1), arms an :class:`~appliance.hardware.aravis.AravisCamera` in software-trigger
    mode for all frames and returns what arrived.

    Parameters
    ----------
    frames_per_camera : dict of str to ndarray, shape (F, H, W), uint8 or uint16
        The frames each camera should deliver.
    base_address : str
        The first camera's loopback address.

    Returns
    -------
    dict of str to ndarray, shape (F, H, W)
        The captured stacks (same dtype as the input).
    """
    first = int(base_address.rsplit(".", 1)[1])
    with fake_gige.LoopbackLab(n_addresses=first - 2 + len(frames_per_camera)) as lab:
        if lab.isolated:
            addresses = [f"127.0.0.{first + k}" for k in range(len(frames_per_camera))]
        else:
            addresses = ["127.0.0.1"] * len(frames_per_camera)

        async def capture_all() -> dict[str, npt.NDArray[Any]]:
            if lab.isolated:
                results = await asyncio.gather(
                    *(
                        _capture_one(name, addr, stack, frame_timeout_ms)
                        for (name, stack), addr in zip(frames_per_camera.items(), addresses, strict=True)
                    )
                )
                return dict(zip(frames_per_camera, results, strict=True))
            out = {}
            for name, stack in frames_per_camera.items():
                out[name] = await _capture_one(name, "127.0.0.1", stack, frame_timeout_ms)
            return out

        return lab.call(asyncio.run, capture_all())


async def _capture_one(
    name: str, address: str, stack: npt.NDArray[Any], frame_timeout_ms: float
) -> npt.NDArray[Any]:
    fmt = "Mono8" if stack.dtype == np.uint8 else "Mono16"
    serial = f"FAKE-{name}"[:15]
    fake = await asyncio.to_thread(fake_gige.start_fake_camera, address, serial, stack)
    cam = aravis_backend.AravisCamera(
        name,
        AravisCameraConfig(
            address=address,
            pixel_format=fmt,
            trigger="Software",
            exposure_us=20000,
            frame_timeout_ms=frame_timeout_ms,
        ),
    )
    try:
        await cam.open()
        out = np.empty_like(stack)
        await cam.arm(len(stack), out)
        await cam.wait_frames(len(stack) * frame_timeout_ms / 1000 + 5)
        return out
    finally:
        await cam.close()
        await asyncio.to_thread(fake.stop)


# --- no camera needed ----------------------------------------------------------------------------------


def test_missing_gi_names_the_packages(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "gi", None)
    with pytest.raises(BackendUnavailableError, match=r"gir1\.2-aravis-0\.8"):
        aravis_backend.load_aravis()


def test_host_names_are_refused_to_avoid_discovery() -> None:
    with pytest.raises(CameraError, match="not an IPv4 address"):
        aravis_backend.AravisCamera("left", AravisCameraConfig(address="camera.local"))


def test_probe_refuses_host_names() -> None:
    from appliance.hardware.devices_probe import probe_aravis

    assert "not an IPv4 address" in probe_aravis("camera.local")


# --- discovery: only inside the private namespace, where loopback is the only interface --------------------


def _require_isolation(lab: fake_gige.LoopbackLab) -> None:
    if not lab.isolated:
        pytest.skip(f"discovery broadcasts: only inside a private network namespace ({lab.setup_error})")


def test_open_by_serial_and_discover_inside_the_namespace(lab: fake_gige.LoopbackLab, procs: Processes) -> None:
    from appliance.hardware.devices_probe import discover_aravis

    _require_isolation(lab)
    host_ns = os.readlink("/proc/thread-self/ns/net")

    async def scenario() -> None:
        # threads (and processes) started from the lab's thread live in its namespace, not the host's
        assert await asyncio.to_thread(os.readlink, "/proc/thread-self/ns/net") != host_ns
        procs.tool(addr(lab, 1))  # serial TOOLFAKE
        await asyncio.sleep(0.3)
        found = await asyncio.to_thread(discover_aravis)  # waits for answers: not on the loop
        assert any("serial TOOLFAKE" in d and addr(lab, 1) in d for d in found), found
        cam = camera("left", None, serial="TOOLFAKE")
        try:
            info = await cam.open()
            assert info.serial == "TOOLFAKE"
            out, order = await capture(cam, 3, (info.height, info.width))
        finally:
            await cam.close()
        assert order == [0, 1, 2] and out.max() > 100
        missing = camera("right", None, serial="NOSUCHCAMERA", reconnect_timeout_s=0.0)
        with pytest.raises(CameraError, match="NOSUCHCAMERA"):
            await missing.open()
        await missing.close()

    assert lab.call(os.readlink, "/proc/thread-self/ns/net") != host_ns
    run(lab, scenario)
