"""numba's on-disk kernel cache, in a folder keyed by the kernel sources, and the vector width of the kernels
(imported by every kernel module, before any kernel is defined).

numba decides whether a cached kernel is current from its own file's timestamp only: a kernel that inlines
a helper from another file (the camera-camera filter uses ``_filter_kernels.near_neighbours``, every
projection uses ``geometry/_distortion_kernels.distort_jac``) would run stale code after that file changed,
e.g. after an upgrade that keeps ``/var/cache/scan3d``. So the cache lives in ``<NUMBA_CACHE_DIR>/src-<hash>``,
the hash of every kernel source: any change to any of them starts a fresh folder. Without ``NUMBA_CACHE_DIR``
numba keeps its default (``__pycache__`` beside the sources) and this module changes nothing.

LLVM vectorises with 256-bit registers on every x86 processor by default, AVX-512 ones included, because the
first of them (Skylake-SP, Cascade Lake) lowered their clock under 512-bit work. The decoder's loops are bound
by computation (two cores run them 1.8x faster than one), so on a processor whose AVX-512 does not cost clock
:func:`wide_vector_features` asks LLVM for 512-bit vectors: decoding the camera-camera bench's two stacks
took 44 -> 40 ms, the reference workload 107 -> 101 ms (alternating processes, the same frames). Setting
``NUMBA_CPU_NAME`` or ``NUMBA_CPU_FEATURES`` leaves numba's choice alone.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
from pathlib import Path
from typing import Any

from numba.core import codegen as _numba_codegen_module
from numba.core import config as _numba_config

config: Any = _numba_config  # numba's settings module (its attributes are made at run time)
_numba_codegen: Any = _numba_codegen_module  # untyped

_KEY_DIR = re.compile(r"src-[0-9a-f]{12}")
"""Name of a keyed cache folder (:func:`source_key`)."""

KERNEL_FILES = (
    "reconstruct/_cell_kernels.py", "reconstruct/_decode_kernels.py", "reconstruct/_edge_kernels.py",
    "reconstruct/_filter_kernels.py", "reconstruct/_geom_kernels.py", "reconstruct/_ghost_kernels.py",
    "reconstruct/_hdr_kernels.py", "reconstruct/_normal_kernels.py",
    "reconstruct/_procam_kernels.py", "reconstruct/_stereo_kernels.py", "reconstruct/_visibility_kernels.py",
    "reconstruct/_walled_kernels.py",
    "reconstruct/fuse.py", "sim/_sim_kernels.py", "calibration/_kernels.py", "geometry/_distortion_kernels.py",
)  # fmt: skip
"""Every module of ``appliance`` with numba kernels (a test keeps the list complete)."""


def source_key() -> str:
    """Short hash (12 hex) of every kernel source file."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for rel in KERNEL_FILES:
        h.update(rel.encode() + b"\0")
        try:
            h.update((root / rel).read_bytes())
        except OSError:
            h.update(b"(missing)")
    return h.hexdigest()[:12]


def kernels_on_disk(kernel: Any) -> tuple[bool, str] | None:
    """Whether numba holds compiled code of the jitted ``kernel`` on disk for its current source, and the folder
    it uses (numba's own choice: ``NUMBA_CACHE_DIR``, ``__pycache__`` beside the source, or a per-user folder).
    Only code built for this processor and these features counts (the index keeps other builds too). None
    when numba's cache cannot tell (its internals differ). False means the next use compiles."""
    try:
        cache = kernel._cache
        tm = kernel.targetctx.codegen().magic_tuple()  # the processor and features kernels are built for now
        index = cache._cache_file._load_index()
        return any(key[1] == tm for key in index), str(cache._cache_path)
    except Exception:  # numba internals of another version, or an unreadable folder: nothing to report
        return None


def prune_stale(keep_others: int = 1) -> list[Path]:
    """Delete the compiled kernels of older sources under ``NUMBA_CACHE_DIR``: every ``src-<hash>`` folder but
    the current one and the ``keep_others`` most recently used others (a rollback finds them). Each upgrade
    otherwise leaves ~25-40 MB behind, for ever, on a box nobody looks at.

    Only folders named like ours are touched, never links or other files; one that cannot be deleted stays
    (a later start tries again). Without ``NUMBA_CACHE_DIR`` (numba's ``__pycache__`` beside the sources)
    nothing is pruned. Returns the folders deleted.
    """
    current = Path(config.CACHE_DIR) if config.CACHE_DIR else None
    if current is None or not _KEY_DIR.fullmatch(current.name):
        return []
    try:
        others = [p for p in current.parent.iterdir()
                  if p != current and _KEY_DIR.fullmatch(p.name) and p.is_dir() and not p.is_symlink()]  # fmt: skip
        others.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    except OSError:
        return []
    gone = []
    for old in others[max(keep_others, 0) :]:
        try:
            shutil.rmtree(old)
        except OSError:
            continue
        gone.append(old)
    return gone


PREFER_WIDE = "-prefer-256-bit"
"""The feature that lifts LLVM's 256-bit preference (in ``config.CPU_FEATURES`` when the kernels use 512)."""

NARROW_AVX512 = frozenset({"skylake-avx512", "cascadelake", "cooperlake", "cannonlake", "knl", "knm"})
"""LLVM's names of the processors whose clock drops under 512-bit work: they keep 256-bit vectors."""


def wide_vector_features(cpu_name: str, features: str) -> str | None:
    """numba's CPU feature string that prefers 512-bit vectors, or None to keep LLVM's default.

    Parameters
    ----------
    cpu_name : str
        LLVM's name of the host processor (``llvmlite.binding.get_host_cpu_name()``).
    features : str
        LLVM's feature string of the host (``+avx512f,+avx512bw,...,-amx-tile``).

    Returns
    -------
    str or None
        ``features`` with :data:`PREFER_WIDE` added when the host has AVX-512 F, BW and VL and is not one of
        :data:`NARROW_AVX512`; None otherwise.
    """
    have = {f[1:] for f in features.split(",") if f.startswith("+")}
    if cpu_name in NARROW_AVX512 or not {"avx512f", "avx512bw", "avx512vl"} <= have:
        return None
    return f"{features},{PREFER_WIDE}"


def _configure() -> None:
    if config.CPU_NAME is None and config.CPU_FEATURES is None:  # the operator chose nothing (env or file)
        try:  # numba's own view of the host (its llvmlite binding)
            cg = _numba_codegen
            wide = wide_vector_features(cg.ll.get_host_cpu_name(), cg.get_host_cpu_features())
        except Exception:  # an llvmlite that cannot tell: LLVM's default
            wide = None
        if wide is not None:
            config.CPU_FEATURES = wide
    base = os.environ.get("NUMBA_CACHE_DIR") or config.CACHE_DIR  # the env may be set after numba's import
    if base and not Path(base).name.startswith("src-"):
        config.CACHE_DIR = os.path.join(base, f"src-{source_key()}")


_configure()
