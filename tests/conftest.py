"""Shared fixtures and paths."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from loopguard import THREAD_GRACE_S, slow_callbacks

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

os.environ.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))


def shared_data(*parts: str) -> Path:
    """A path under ../shared/data; skips the test when that folder is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data {p} is not present beside the repository")
    return p


@pytest.fixture
def without_pygame(monkeypatch: pytest.MonkeyPatch) -> None:
    """The interpreter as where pygame is not installed (``importlib.util.find_spec`` finds no such module)."""
    real = importlib.util.find_spec

    def find_spec(name: str, package: str | None = None) -> importlib.machinery.ModuleSpec | None:
        return None if name.split(".")[0] == "pygame" else real(name, package)

    monkeypatch.setattr(importlib.util, "find_spec", find_spec)


@pytest.fixture
def loop_guard(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Fail the test when one event-loop callback computes or blocks on the loop for too long (see
    :func:`slow_callbacks`), or when a thread the test started is still running :data:`THREAD_GRACE_S` after
    it. Warm numba's kernels before the measured part: the first call of a kernel compiles or loads it.
    """
    before = set(threading.enumerate())
    with slow_callbacks(monkeypatch) as slow:
        yield
    end = time.monotonic() + THREAD_GRACE_S
    leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()]
    while leaked and time.monotonic() < end:
        time.sleep(0.05)
        leaked = [t for t in leaked if t.is_alive()]
    assert not slow, "the event loop was blocked: " + "; ".join(slow[:5])
    assert not leaked, f"threads left running after the test: {[t.name for t in leaked]}"
