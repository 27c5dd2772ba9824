"""Every backend implements its whole protocol: optional capabilities are declared, not probed for, and
``Camera.trigger`` has one (async) signature in every backend."""

from __future__ import annotations

import asyncio
import importlib
import inspect

import numpy as np
import pytest

from appliance.config import parse_config
from appliance.hardware.base import ButtonOnly, Camera, Projector, PulseSource, TriggerSource, pulse_source
from appliance.hardware.registry import build_rig

BACKENDS = {
    Camera: [("sim", "SimCamera"), ("aravis", "AravisCamera"), ("uvc", "UvcCamera")],
    Projector: [("sim", "SimProjector"), ("lightcrafter4500", "LightCrafter4500"), ("display", "DisplayProjector")],
    TriggerSource: [("sim", "SimTrigger"), ("serial", "SerialTrigger"), ("gpio", "GpioTrigger")],
}

SMALL = """
cameras: {cam0: {type: sim}}
sequence: {kind: gray, axes: x, stripe_px: 8}
virtual_rig:
  projector: {width: 320, height: 200, focal_px: 400, principal_px: [160, 100], position_mm: [150, 0, 0],
              look_at_mm: [0, 0, 600]}
  cameras:
    cam0: {width: 160, height: 128, focal_px: 260, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}
"""


def members(protocol: type) -> set[str]:
    names = set()
    for cls in protocol.__mro__:
        if cls in (object,) or cls.__name__ in ("Protocol", "Generic"):
            continue
        names |= {n for n in vars(cls) if not n.startswith("_")} | set(getattr(cls, "__annotations__", {}))
    return names


def backend_class(module: str, name: str) -> type:
    try:
        return getattr(importlib.import_module(f"appliance.hardware.{module}"), name)  # type: ignore[no-any-return]
    except ImportError as exc:  # an optional library is missing: only that backend is unavailable
        pytest.skip(f"backend {module}: {exc}")


@pytest.mark.parametrize(
    ("protocol", "module", "name"), [(p, m, n) for p, items in BACKENDS.items() for m, n in items]
)
def test_backend_has_every_member_of_its_protocol(protocol: type, module: str, name: str) -> None:
    cls = backend_class(module, name)
    wanted = members(protocol) - {"name"}  # set per instance
    missing = sorted(m for m in wanted if not hasattr(cls, m))
    assert not missing, f"{name} lacks {missing} of {protocol.__name__}"
    for m in wanted:
        proto_member = getattr(protocol, m)
        if inspect.iscoroutinefunction(proto_member):
            assert inspect.iscoroutinefunction(getattr(cls, m)), f"{name}.{m} must be async like the protocol"
    if protocol is Camera:
        params = list(inspect.signature(cls.trigger).parameters)
        assert params[:2] == ["self", "index"], f"{name}.trigger{inspect.signature(cls.trigger)}"


def test_only_the_controller_is_a_pulse_source() -> None:
    serial = backend_class("serial", "SerialTrigger")
    assert serial.emits_sequence_pulses and serial.has_lamps
    assert inspect.iscoroutinefunction(serial.run_sequence)
    for module, name in (("sim", "SimTrigger"), ("gpio", "GpioTrigger")):
        cls = backend_class(module, name)
        assert issubclass(cls, ButtonOnly) and not cls.emits_sequence_pulses and not cls.has_lamps
        assert not hasattr(cls, "run_sequence")  # the scan's old probe keeps finding nothing


def test_pulse_source_and_button_defaults() -> None:
    rig = build_rig(parse_config(SMALL, "small.yaml"))
    trig = rig.trigger
    assert isinstance(trig, TriggerSource) and pulse_source(trig) is None
    assert trig.status() == "open"
    asyncio.run(trig.set_leds(True, False, False))  # no lamps: nothing happens, nothing fails

    class Controller(ButtonOnly):
        name = "controller"
        emits_sequence_pulses = True

        async def open(self) -> None: ...
        async def next_event(self) -> object: ...
        async def close(self) -> None: ...

        async def run_sequence(self, n: int) -> list[int]:
            return list(range(n))

    c = Controller()
    assert isinstance(c, PulseSource) and pulse_source(c) is c  # type: ignore[arg-type]
    c.emits_sequence_pulses = False
    assert pulse_source(c) is None  # type: ignore[arg-type]


def test_sim_camera_takes_software_triggers_like_the_projector_s() -> None:
    """``await camera.trigger(i)`` exposes frame i of the sim camera, as the simulated projector does."""
    rig = build_rig(parse_config(SMALL, "small.yaml"))
    cam = rig.cameras["cam0"]
    assert isinstance(cam, Camera) and cam.needs_software_trigger is False

    async def run() -> tuple[np.ndarray, np.ndarray]:
        from appliance.patterns.from_config import build_sequence

        assert rig.virtual is not None
        seq = build_sequence(parse_config(SMALL).sequence, 320, 200)
        await rig.projector.load(seq)
        info = await cam.open()
        try:
            by_projector = np.zeros((len(seq), info.height, info.width), np.uint8)
            await cam.arm(len(seq), by_projector)
            await rig.projector.start()
            await cam.wait_frames(30)
            by_software = np.zeros_like(by_projector)
            await cam.arm(len(seq), by_software)
            for i in range(len(seq)):
                await cam.trigger(i)
            await cam.wait_frames(30)
        finally:
            await cam.close()
        return by_projector, by_software

    a, b = asyncio.run(run())
    assert a.max() > 100
    # the same scene and patterns (the camera noise differs per exposure)
    assert np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16))) < 4
