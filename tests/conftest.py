"""Shared fixtures and paths."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
from pathlib import Path

import pytest

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
