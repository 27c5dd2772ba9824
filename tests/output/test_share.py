"""The share writer: atomic files under YYYY-MM-DD/, the spool while the share is away, order, retention."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scan_builders import SHAPES, cloud, meta
from share_watch import DirWatch

from appliance.config.schema import OutputConfig
from appliance.errors import OutputError
from appliance.output import share as S
from appliance.output import spool
from appliance.output.atomic import TMP_PREFIX
from appliance.output.ply import read_ply_vertices


def xyz(path: Path) -> np.ndarray:
    v = read_ply_vertices(path)
    return np.stack([v["x"], v["y"], v["z"]], axis=1)


@pytest.fixture
def dirs(tmp_path: Path) -> SimpleNamespace:
    share = tmp_path / "share"
    share.mkdir()
    return SimpleNamespace(share=share, spool=tmp_path / "spool", away=tmp_path / "share-away")


def writer(d: SimpleNamespace, **kw: object) -> S.ShareWriter:
    kw.setdefault("min_free_mb", 0)
    cfg = OutputConfig(directory=d.share, spool_directory=d.spool, **kw)  # type: ignore[arg-type]
    return S.ShareWriter(cfg)


@pytest.fixture
def full_disk(monkeypatch: pytest.MonkeyPatch) -> Iterator[set[str]]:
    """Paths (prefixes) in this set report 1 MB free through the statvfs hook."""
    full: set[str] = set()
    real = S.STATVFS

    def fake(path: str) -> object:
        if any(path.startswith(p) for p in full):
            return SimpleNamespace(f_bavail=256, f_frsize=4096)
        return real(path)

    monkeypatch.setattr(S, "STATVFS", fake)
    yield full


def no_temp_files(*roots: Path) -> bool:
    return not any(p.name.startswith(TMP_PREFIX) for r in roots if r.exists() for p in r.rglob("*"))


def test_scan_goes_to_the_dated_share_folder_complete(dirs: SimpleNamespace) -> None:
    w = writer(dirs)
    c = cloud()
    out = w.write_scan("2026-01-01", meta(1), c, SHAPES)
    assert out.location == "share"
    folder = dirs.share / "2026-01-01"
    assert sorted(p.name for p in folder.iterdir()) == [
        f"{meta(1).scan_id}{s}" for s in (".json", ".ply", ".png")
    ]
    np.testing.assert_array_equal(xyz(folder / f"{meta(1).scan_id}.ply"), c.xyz)
    side = json.loads((folder / f"{meta(1).scan_id}.json").read_text())
    assert side["files"]["cloud"] == f"{meta(1).scan_id}.ply"
    assert no_temp_files(dirs.share) and w.spool_entries() == []


def test_share_away_spools_then_moves_over_in_order(dirs: SimpleNamespace) -> None:
    w = writer(dirs)
    w.write_scan("2026-01-01", meta(1), cloud(seed=1), SHAPES)
    dirs.share.rename(dirs.away)  # unmounted / removed
    outs = [w.write_scan("2026-01-01", meta(i), cloud(seed=i), SHAPES) for i in (2, 3, 4)]
    assert [o.location for o in outs] == ["spool"] * 3
    assert "not there" in outs[0].reason
    assert not dirs.share.exists(), (
        "the writer must never create the share root (it would fill the local disk)"
    )
    assert [e.name.split("-", 1)[1] for e in w.spool_entries()] == [meta(i).scan_id for i in (2, 3, 4)]
    assert w.flush_spool() == []  # still away: nothing moves
    dirs.away.rename(dirs.share)
    folder = dirs.share / "2026-01-01"
    watch = DirWatch(folder)  # the kernel's record of what appeared on the share, in order
    moved = w.flush_spool()
    assert [m.scan_id for m in moved] == [meta(i).scan_id for i in (2, 3, 4)]
    for i in (1, 2, 3, 4):
        np.testing.assert_array_equal(xyz(folder / f"{meta(i).scan_id}.ply"), cloud(seed=i).xyz)
        assert (folder / f"{meta(i).scan_id}.json").is_file() and (
            folder / f"{meta(i).scan_id}.png"
        ).is_file()
    # the sidecars appeared in scan order, each after its cloud and preview (a rename keeps the mtime, so
    # the order is taken from inotify's record of the renames, not from timestamps)
    assert watch.appeared(".json") == [meta(i).scan_id for i in (2, 3, 4)]
    assert watch.appeared(".ply") == [meta(i).scan_id for i in (2, 3, 4)]
    assert watch.partial_moments() == []
    log = [n for kind, n in watch.poll() if kind == "+"]
    for i in (2, 3, 4):
        sid = meta(i).scan_id
        assert log.index(f"{sid}.json") > max(log.index(f"{sid}.ply"), log.index(f"{sid}.png"))
    watch.close()
    assert w.spool_entries() == [] and no_temp_files(dirs.share, dirs.spool)


def test_new_scan_waits_behind_spooled_ones(dirs: SimpleNamespace, full_disk: set[str]) -> None:
    w = writer(dirs, min_free_mb=1)
    full_disk.add(str(dirs.share))
    assert w.write_scan("2026-01-01", meta(1), cloud(), SHAPES).location == "spool"
    assert "full" in w.last_reason
    full_disk.clear()
    out = w.write_scan("2026-01-01", meta(2), cloud(), SHAPES)  # flushes scan 1 first, then writes scan 2
    assert out.location == "share"
    assert sorted(p.stem for p in (dirs.share / "2026-01-01").glob("*.json")) == [
        meta(1).scan_id,
        meta(2).scan_id,
    ]


def test_storage_guard_refuses_when_share_and_spool_are_full(
    dirs: SimpleNamespace, full_disk: set[str]
) -> None:
    w = writer(dirs, min_free_mb=2)
    need = S.estimate_scan_bytes(SHAPES, normals=False, preview=True)
    assert w.storage_problem(need) == ""
    full_disk.add(str(dirs.share))
    assert w.storage_problem(need) == ""  # the spool still takes it
    full_disk.add(str(dirs.spool))
    problem = w.storage_problem(need)
    assert "full" in problem and "spool" in problem
    with pytest.raises(OutputError, match="cannot be stored"):
        w.write_scan("2026-01-01", meta(1), cloud(), SHAPES)
    assert no_temp_files(dirs.share, dirs.spool)


def test_spool_size_limit_is_part_of_the_guard(dirs: SimpleNamespace) -> None:
    w = writer(dirs, spool_max_mb=0.5)
    dirs.share.rename(dirs.away)
    w.write_scan("2026-01-01", meta(1), cloud(), SHAPES)
    held = w.spool_bytes()
    assert 0 < held < 0.5 * S.MB
    assert w.storage_problem(int(0.5 * S.MB) - held - 1) == ""
    assert "spool_max_mb" in w.storage_problem(int(0.5 * S.MB) - held + 1)


def test_retention_drops_old_and_oversize_entries(dirs: SimpleNamespace) -> None:
    w = writer(dirs, spool_max_age_days=1)
    dirs.share.rename(dirs.away)
    for i in (1, 2, 3):
        w.write_scan("2026-01-01", meta(i), cloud(), SHAPES)
    entries = w.spool_entries()
    old = time.time() - 3 * 86400
    os.utime(entries[0], (old, old))
    assert w.enforce_retention() == [entries[0].name]
    assert [e.name for e in w.spool_entries()] == [e.name for e in entries[1:]]
    small = S.ShareWriter(
        OutputConfig(
            directory=dirs.share,
            spool_directory=dirs.spool,
            spool_max_mb=spool.dir_bytes(entries[2]) * 1.5 / S.MB,
        )
    )
    assert small.enforce_retention() == [entries[1].name]  # oldest first until under the limit
    assert w.spool_entries()[0].name == entries[2].name


def test_crash_leftovers_are_cleaned(dirs: SimpleNamespace) -> None:
    w = writer(dirs)
    dirs.spool.mkdir()
    (dirs.spool / f"{TMP_PREFIX}00000001-x").mkdir()
    (dirs.spool / f"{TMP_PREFIX}00000001-x" / "a.ply").write_bytes(b"partial")
    assert w.cleanup_incomplete() == 1
    assert w.spool_entries() == [] and no_temp_files(dirs.spool)


def test_status_reports_share_and_spool(dirs: SimpleNamespace) -> None:
    w = writer(dirs)
    st = w.status()
    assert st["available"] and st["spooled_scans"] == 0 and st["free_mb"] > 0
    dirs.share.rename(dirs.away)
    w.write_scan("2026-01-01", meta(1), cloud(), SHAPES)
    st = w.status()
    assert not st["available"] and "not there" in st["problem"] and st["spooled_scans"] == 1


def test_require_mount(dirs: SimpleNamespace) -> None:
    w = writer(dirs, require_mount=True)
    assert "mount point" in w.share_problem()
    assert w.write_scan("2026-01-01", meta(1), cloud(), SHAPES).location == "spool"


# --- spool entries after crashes: idempotent moves, quarantine ----------------------------------------------


def spool_two_scans(dirs: SimpleNamespace) -> tuple[S.ShareWriter, list[Path]]:
    """Scans 1 and 2 spooled while the share is away; the share back (with today's folder)."""
    w = writer(dirs)
    dirs.share.rename(dirs.away)
    for i in (1, 2):
        assert w.write_scan("2026-01-01", meta(i), cloud(seed=i), SHAPES).location == "spool"
    dirs.away.rename(dirs.share)
    (dirs.share / "2026-01-01").mkdir()
    return w, w.spool_entries()


def assert_complete_on_share(dirs: SimpleNamespace, i: int) -> None:
    folder = dirs.share / "2026-01-01"
    sid = meta(i).scan_id
    np.testing.assert_array_equal(xyz(folder / f"{sid}.ply"), cloud(seed=i).xyz)
    assert json.loads((folder / f"{sid}.json").read_text())["scan_id"] == sid
    assert (folder / f"{sid}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_spool_entry_moved_half_way_is_finished_not_blocking(dirs: SimpleNamespace) -> None:
    """A crash between the per-file renames of a move left the cloud on the share and the rest in the spool.

    The old mover renamed the files one by one and stopped for good at the missing source ("stays in the
    spool"), so every later scan spooled behind it.
    """
    w, entries = spool_two_scans(dirs)
    sid = meta(1).scan_id
    os.rename(entries[0] / f"{sid}.ply", dirs.share / "2026-01-01" / f"{sid}.ply")  # the crash's state
    moved = w.flush_spool()
    assert [m.scan_id for m in moved] == [meta(1).scan_id, meta(2).scan_id]
    assert w.spool_entries() == [] and w.quarantined == 0
    for i in (1, 2):
        assert_complete_on_share(dirs, i)
    assert w.write_scan("2026-01-01", meta(3), cloud(seed=3), SHAPES).location == "share"
    assert no_temp_files(dirs.share, dirs.spool)


def test_spool_entry_already_on_the_share_counts_as_moved(dirs: SimpleNamespace) -> None:
    """A crash after the sidecar's rename, before the entry was removed: nothing is written twice."""
    w, entries = spool_two_scans(dirs)
    folder = dirs.share / "2026-01-01"
    for p in entries[0].iterdir():
        if p.name != spool.ENTRY_FILE:
            (folder / p.name).write_bytes(p.read_bytes())
    inodes = {p.name: p.stat().st_ino for p in folder.iterdir()}
    watch = DirWatch(folder)
    moved = w.flush_spool()
    assert [m.scan_id for m in moved] == [meta(1).scan_id, meta(2).scan_id]
    assert {p.name: p.stat().st_ino for p in folder.iterdir() if p.name in inodes} == inodes  # untouched
    assert watch.appeared(".json") == [meta(2).scan_id]  # only scan 2 was written
    watch.close()
    for i in (1, 2):
        assert_complete_on_share(dirs, i)


def test_spool_entry_with_a_different_file_on_the_share_is_overwritten(dirs: SimpleNamespace) -> None:
    w, _ = spool_two_scans(dirs)
    sid = meta(1).scan_id
    (dirs.share / "2026-01-01" / f"{sid}.ply").write_bytes(b"ply\nsomething else\n")
    assert len(w.flush_spool()) == 2
    assert_complete_on_share(dirs, 1)


@pytest.mark.parametrize("damage", ["empty entry.json", "binary entry.json", "file changed", "file gone"])
def test_broken_spool_entry_is_quarantined_and_the_queue_goes_on(
    dirs: SimpleNamespace, damage: str, caplog: pytest.LogCaptureFixture
) -> None:
    """``entry.json`` lost its content (written without fsync before a power cut), or a file of the entry
    changed or went missing: the old writer stopped at it for good; now it goes to quarantine, one line."""
    w, entries = spool_two_scans(dirs)
    sid = meta(1).scan_id
    if damage == "empty entry.json":
        (entries[0] / spool.ENTRY_FILE).write_bytes(b"")
    elif damage == "binary entry.json":
        (entries[0] / spool.ENTRY_FILE).write_bytes(b"\xff\xfe\x00garbage")
    elif damage == "file changed":
        with open(entries[0] / f"{sid}.ply", "r+b") as f:
            f.seek(-4, os.SEEK_END)
            f.write(b"XXXX")
    else:
        (entries[0] / f"{sid}.png").unlink()
    caplog.set_level("WARNING", logger="appliance.output.spool")
    moved = w.flush_spool()
    assert [m.scan_id for m in moved] == [meta(2).scan_id]
    assert_complete_on_share(dirs, 2)
    assert w.spool_entries() == [] and w.quarantined == 1
    assert (dirs.spool / spool.QUARANTINE_DIR / entries[0].name).is_dir()
    lines = [r.getMessage() for r in caplog.records if "quarantined" in r.getMessage()]
    assert len(lines) == 1 and entries[0].name in lines[0] and "\n" not in lines[0]
    folder = dirs.share / "2026-01-01"
    assert not (folder / f"{sid}.json").exists()
    assert not (folder / f"{sid}.ply").exists() and no_temp_files(dirs.share)  # nothing of it is visible
    assert w.status()["spool_quarantined"] == 1


def test_spool_folder_without_entry_json_is_quarantined_at_start(dirs: SimpleNamespace) -> None:
    w, entries = spool_two_scans(dirs)
    (entries[0] / spool.ENTRY_FILE).unlink()
    assert w.cleanup_incomplete() == 0
    assert w.spool_entries() == [entries[1]] and w.quarantined == 1
    assert [m.scan_id for m in w.flush_spool()] == [meta(2).scan_id]


def test_spool_entry_json_names_sizes_and_checksums(dirs: SimpleNamespace) -> None:
    _, entries = spool_two_scans(dirs)
    info = json.loads((entries[0] / spool.ENTRY_FILE).read_text())
    assert info["day"] == "2026-01-01" and info["scan_id"] == meta(1).scan_id
    assert [f["name"] for f in info["files"]] == [f"{meta(1).scan_id}{s}" for s in (".ply", ".png", ".json")]
    import hashlib

    for f in info["files"]:
        data = (entries[0] / f["name"]).read_bytes()
        assert f["size"] == len(data) and f["sha256"] == hashlib.sha256(data).hexdigest()


def test_share_out_of_inodes_is_not_available(dirs: SimpleNamespace, monkeypatch: pytest.MonkeyPatch) -> None:
    real = S.STATVFS

    def few_inodes(path: str) -> object:
        st = real(path)
        if path.startswith(str(dirs.share)):
            return SimpleNamespace(f_bavail=st.f_bavail, f_frsize=st.f_frsize, f_files=1000, f_favail=3)
        return st

    monkeypatch.setattr(S, "STATVFS", few_inodes)
    w = writer(dirs)
    assert "out of inodes" in w.share_problem()
    out = w.write_scan("2026-01-01", meta(1), cloud(), SHAPES)
    assert out.location == "spool" and "inodes" in out.reason
    assert not w.status()["available"]


def test_start_removes_old_temporary_files_not_a_write_in_progress(dirs: SimpleNamespace) -> None:
    """A temporary file an older writer (without the journal) left an hour ago goes at start; a fresh one,
    perhaps another appliance's write in progress on the same share, stays."""
    folder = dirs.share / "2026-01-02"
    folder.mkdir()
    old, fresh = folder / f"{TMP_PREFIX}x-000001.ply.123", folder / f"{TMP_PREFIX}y-000001.ply.456"
    old.write_bytes(b"partial")
    fresh.write_bytes(b"in progress")
    t = time.time() - S.STALE_TMP_S - 60
    os.utime(old, (t, t))
    assert writer(dirs).cleanup_incomplete() == 1
    assert not old.exists() and fresh.exists()
