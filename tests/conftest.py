"""Shared fixtures and paths."""

from __future__ import annotations

import gc
import importlib.machinery
import importlib.util
import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from loopguard import guard

pytest_plugins = ("pytester",)

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


@pytest.fixture(autouse=True)
def _guard_every_event_loop(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """The loop guard around every test (:func:`loopguard.guard`), so a test that runs an event loop (``asyncio.run``,
    a service, a client) cannot run it unguarded: it fails when one event-loop callback computes or blocks on the
    loop for too long, or when the test ran a loop and a thread it started is still running
    :data:`loopguard.THREAD_GRACE_S` after it. Autouse rather than a check that asks each test to opt in: the
    guard costs nothing where no loop runs, and a new async test is guarded without anyone remembering to.
    Warm numba's kernels before the measured part: the first call of a kernel compiles or loads it.
    """
    limits = request.node.get_closest_marker("loop_guard_limits")
    kw = dict(limits.kwargs) if limits is not None else {}
    kw.pop("reason", None)
    # the young garbage earlier tests left is collected here, before this test's loop: its finalizers (a file
    # on a share a test hung, a device a test closed) are theirs, not this test's (the full suite once charged a
    # LightCrafter test 4.4 s of a young collection with 3 ms of CPU: a finalizer waiting on something)
    gc.collect(1)
    with guard(monkeypatch, check_threads="loop_guard" in request.fixturenames, **kw):
        yield


@pytest.fixture
def loop_guard() -> None:
    """The thread rule of the loop guard even for a test that runs no event loop itself (the guard runs around
    every test; see :func:`_guard_every_event_loop`)."""
