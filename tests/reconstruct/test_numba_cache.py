"""numba's cache folder is keyed by every kernel source, so a change in one file never leaves stale kernels."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

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
    generic = subprocess.run(run, env={**env, "NUMBA_CPU_NAME": "generic"}, capture_output=True, text=True,
                             timeout=300, check=True).stdout.splitlines()  # fmt: skip
    assert generic[0].startswith(f"(False, '{folder}"), generic  # built for another processor: compiles again


def test_prune_stale_keeps_the_current_and_the_newest_other(tmp_path: Path, monkeypatch: Any) -> None:
    root = tmp_path / "cache"
    current = root / "src-aaaaaaaaaaaa"
    olds = [root / f"src-{c * 12}" for c in "bcd"]
    for k, d in enumerate([current, *olds]):
        (d / "reconstruct_x").mkdir(parents=True)
        (d / "reconstruct_x" / "k.nbi").write_bytes(b"x")
        os.utime(d, (1_000_000 + k, 1_000_000 + k))  # b oldest, d newest
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (root / "src-eeeeeeeeeeee").symlink_to(elsewhere)  # a link: never followed or removed
    (root / "src-ffffffffffff").write_text("a file")  # not a folder
    (root / "src-notahash00").mkdir()  # not our name
    (root / "notes").mkdir()
    monkeypatch.setattr(nc.config, "CACHE_DIR", str(current))
    gone = nc.prune_stale(keep_others=1)
    assert sorted(gone) == sorted(olds[:2])
    left = sorted(p.name for p in root.iterdir())
    assert left == ["notes", "src-aaaaaaaaaaaa", "src-dddddddddddd", "src-eeeeeeeeeeee", "src-ffffffffffff",
                    "src-notahash00"]  # fmt: skip
    assert elsewhere.is_dir() and (current / "reconstruct_x" / "k.nbi").exists()
    assert nc.prune_stale(keep_others=1) == []  # nothing more to do
    monkeypatch.setattr(nc.config, "CACHE_DIR", str(tmp_path / "plain"))  # not a keyed folder: hands off
    assert nc.prune_stale(keep_others=0) == []
    assert (root / "src-dddddddddddd").is_dir()


def test_wide_vectors_only_where_avx512_costs_no_clock() -> None:
    avx512 = "+sse4.2,+avx2,+avx512f,+avx512bw,+avx512vl,+avx512dq,-amx-tile"
    assert nc.wide_vector_features("sapphirerapids", avx512) == avx512 + ",-prefer-256-bit"
    assert nc.wide_vector_features("znver4", avx512) == avx512 + ",-prefer-256-bit"
    for slow in ("skylake-avx512", "cascadelake"):  # 512-bit work lowers their clock
        assert nc.wide_vector_features(slow, avx512) is None
    assert nc.wide_vector_features("alderlake", "+sse4.2,+avx2,-avx512f,-avx512bw,-avx512vl") is None
    assert nc.wide_vector_features("x", "+avx512f,+avx512vl,-avx512bw") is None  # no byte/word ops: the decoder's


def _codegen_features(env: dict[str, str]) -> tuple[str, str, str]:
    code = (
        "import llvmlite.binding as llvm\n"
        "from numba.core import codegen\n"
        "from numba.core.registry import cpu_target\n"
        "import appliance.reconstruct._filter_kernels\n"
        "print(llvm.get_host_cpu_name()); print(codegen.get_host_cpu_features())\n"
        "print(cpu_target.target_context.codegen()._tm_features)\n"
    )
    base = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES")}
    out = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True,
                         timeout=300, check=True)  # fmt: skip
    name, host, used = out.stdout.strip().splitlines()[-3:]
    return name, host, used


def test_the_kernels_compile_with_the_chosen_width_and_a_set_numba_cpu_wins() -> None:
    name, host, used = _codegen_features({})
    assert used == (nc.wide_vector_features(name, host) or host)  # the codegen numba builds kernels with
    _, _, used = _codegen_features({"NUMBA_CPU_FEATURES": host})
    assert used == host  # the operator's setting stands
