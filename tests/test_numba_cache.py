"""numba's cache folder is keyed by every kernel source, so a change in one file never leaves stale kernels."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import appliance._numba_cache as nc

ROOT = Path(nc.__file__).resolve().parent


def test_every_kernel_module_is_listed_and_imports_the_cache_setup() -> None:
    with_kernels = sorted(str(p.relative_to(ROOT)) for p in ROOT.rglob("*.py") if "@njit" in p.read_text())
    assert with_kernels == sorted(nc.KERNEL_FILES)
    for rel in nc.KERNEL_FILES:
        assert "import appliance._numba_cache" in (ROOT / rel).read_text(), rel


def test_cache_lands_in_a_folder_of_the_sources_hash(tmp_path: Path) -> None:
    code = (
        "import numpy as np, numba\n"
        "from appliance.reconstruct import _filter_kernels as K\n"
        "xyz = np.zeros((4, 4, 3), np.float32); keep = np.zeros((4, 4), np.bool_)\n"
        "K.isolated_keep(xyz, 0, 1.0, keep)\n"
        "print(numba.config.CACHE_DIR)\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300,
                         check=True)  # fmt: skip
    folder = tmp_path / f"src-{nc.source_key()}"
    assert out.stdout.strip().splitlines()[-1] == str(folder)
    assert any(folder.rglob("*.nbi")), "no cache index written in the keyed folder"


def test_the_key_follows_the_sources(tmp_path: Path) -> None:
    before = nc.source_key()
    copy = tmp_path / "appliance"
    for rel in nc.KERNEL_FILES:
        (copy / rel).parent.mkdir(parents=True, exist_ok=True)
        (copy / rel).write_bytes((ROOT / rel).read_bytes())
    fake = copy / "_numba_cache.py"
    fake.write_text("")
    import unittest.mock as um

    with um.patch.object(nc, "__file__", str(fake)):
        assert nc.source_key() == before
        f = copy / nc.KERNEL_FILES[1]
        f.write_text(f.read_text() + "\n# changed\n")
        assert nc.source_key() != before


def test_kernels_on_disk_tells_a_first_run_from_a_cached_one(tmp_path: Path) -> None:
    """What ``scan3d decode`` / ``scan3d scan`` use to say that this run compiles the kernels first."""
    code = (
        "import numpy as np\n"
        "from appliance._numba_cache import kernels_on_disk\n"
        "from appliance.reconstruct import _filter_kernels as K\n"
        "print(kernels_on_disk(K.isolated_keep))\n"
        "xyz = np.zeros((4, 4, 3), np.float32); keep = np.zeros((4, 4), np.bool_)\n"
        "K.isolated_keep(xyz, 0, 1.0, keep)\n"
        "print(kernels_on_disk(K.isolated_keep))\n"
        "print(kernels_on_disk(len))\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    run = [sys.executable, "-c", code]
    first = subprocess.run(run, env=env, capture_output=True, text=True, timeout=300, check=True).stdout.splitlines()
    folder = str(tmp_path / f"src-{nc.source_key()}")
    assert first[0].startswith(f"(False, '{folder}") and first[1].startswith(f"(True, '{folder}"), first
    assert first[2] == "None"  # not a numba kernel: nothing to report
    again = subprocess.run(run, env=env, capture_output=True, text=True, timeout=300, check=True).stdout.splitlines()
    assert again[0].startswith(f"(True, '{folder}"), again  # a later process finds them on disk
