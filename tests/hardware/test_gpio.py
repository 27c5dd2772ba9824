"""GPIO button backend against a fake chip exposing the same fd + edge-event interface."""

from __future__ import annotations

import asyncio
import os
from dataclasses import dataclass

import pytest

from appliance.config.backends import GpioTriggerConfig
from appliance.errors import BackendUnavailableError
from appliance.hardware.gpio import GpioTrigger, request_line_gpiod


@dataclass
class FakeEdgeEvent:
    timestamp_ns: int
    line_offset: int = 17


class FakeLineRequest:
    """A pipe stands in for the line request's fd: an edge makes it readable, like the kernel does."""

    def __init__(self) -> None:
        self._r, self._w = os.pipe()
        self._pending: list[FakeEdgeEvent] = []
        self.released = False

    @property
    def fd(self) -> int:
        return self._r

    def edge(self, t_ns: int) -> None:
        self._pending.append(FakeEdgeEvent(t_ns))
        os.write(self._w, b"x")

    def read_edge_events(self) -> list[FakeEdgeEvent]:
        os.read(self._r, 4096)
        out, self._pending = self._pending, []
        return out

    def release(self) -> None:
        self.released = True
        os.close(self._r)
        os.close(self._w)


def test_presses_are_debounced_and_timestamped() -> None:
    fake = FakeLineRequest()
    cfg = GpioTriggerConfig(debounce_ms=20)

    async def main() -> None:
        trig = GpioTrigger(cfg, request_line=lambda c: fake)
        await trig.open()
        t0 = 1_000_000_000
        fake.edge(t0)
        fake.edge(t0 + 2_000_000)  # bounce 2 ms later
        fake.edge(t0 + 5_000_000)  # bounce
        ev = await asyncio.wait_for(trig.next_event(), 2)
        assert ev.t_monotonic_ns == t0 and ev.source.startswith("gpio:")
        fake.edge(t0 + 300_000_000)  # a second press 300 ms later
        ev2 = await asyncio.wait_for(trig.next_event(), 2)
        assert ev2.t_monotonic_ns == t0 + 300_000_000
        assert trig.presses == 2 and trig.bounces == 2
        await trig.close()
        assert fake.released

    asyncio.run(main())


def test_missing_gpiod_disables_only_this_backend(monkeypatch: pytest.MonkeyPatch) -> None:
    import builtins

    real_import = builtins.__import__

    def no_gpiod(name: str, *a: object, **k: object) -> object:
        if name.startswith("gpiod"):
            raise ImportError("No module named 'gpiod'")
        return real_import(name, *a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(builtins, "__import__", no_gpiod)
    with pytest.raises(BackendUnavailableError, match=r"pip install 'gpiod>=2\.1'"):
        request_line_gpiod(GpioTriggerConfig())
