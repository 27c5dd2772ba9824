"""The atomic writer loses nothing (issue 28): a writer that fails, a full disk or a NUL in the name leave
the old file whole and no temporary file behind."""

from __future__ import annotations

import errno
from pathlib import Path
from typing import BinaryIO

import pytest

from appliance.errors import OutputError
from appliance.output.atomic import write_atomic, write_bytes_atomic, write_files_atomic


@pytest.mark.parametrize("failure", ["writer_bug", "disk_full"])
def test_a_failed_write_keeps_the_old_file(tmp_path: Path, failure: str) -> None:
    path = tmp_path / "maps.npz"
    path.write_bytes(b"old content")

    def writer(f: BinaryIO) -> None:
        f.write(b"half of the new")
        if failure == "disk_full":
            raise OSError(errno.ENOSPC, "No space left on device")
        raise RuntimeError("the encoder failed")

    with pytest.raises(OutputError if failure == "disk_full" else RuntimeError) as exc:
        write_atomic(path, writer)
    if failure == "disk_full":
        assert str(exc.value).startswith(f"{path}: cannot be written (No space left on device)")
    assert path.read_bytes() == b"old content"
    assert [p.name for p in tmp_path.iterdir()] == ["maps.npz"]


def test_a_nul_in_the_name_is_one_output_error(tmp_path: Path) -> None:
    with pytest.raises(OutputError, match="NUL"):
        write_bytes_atomic(tmp_path / "a\x00b.ply", b"x")


class _DiskFullAfter:
    """``open`` for the atomic writer whose n-th file fills the disk half-way through its write."""

    def __init__(self, good_files: int) -> None:
        self.left = good_files

    def __call__(self, path: Path, mode: str) -> BinaryIO:
        f = open(path, mode)  # handed to the writer's with-block
        if self.left == 0:
            real_write = f.write

            def write(data: bytes) -> int:
                real_write(bytes(data)[: len(data) // 2])
                raise OSError(errno.ENOSPC, "No space left on device")

            f.write = write  # type: ignore[method-assign]
        self.left -= 1
        return f


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_a_set_of_files_is_written_all_or_none(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from appliance import atomic_write

    for name in ("a.png", "b.png", "c.yaml"):
        (tmp_path / name).write_bytes(b"old " + name.encode())
    before = _snapshot(tmp_path)
    monkeypatch.setattr(atomic_write, "open", _DiskFullAfter(2), raising=False)
    with pytest.raises(OutputError, match=r"c\.yaml: cannot be written \(No space left on device\)"):
        write_files_atomic(tmp_path, {"a.png": b"new a", "b.png": b"new b", "c.yaml": b"new c"})
    assert _snapshot(tmp_path) == before  # no file replaced, no temporary left
    monkeypatch.undo()
    assert [p.name for p in write_files_atomic(tmp_path, {"a.png": b"new a", "d.png": b"d"})] == ["a.png", "d.png"]
    assert (tmp_path / "a.png").read_bytes() == b"new a" and (tmp_path / "b.png").read_bytes() == b"old b.png"


def test_write_manifest_on_a_full_disk_keeps_the_old_manifest(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    from appliance import atomic_write
    from appliance.patterns.manifest import read_manifest, write_manifest
    from appliance.patterns.sequence import BlackFrame, Sequence, WhiteFrame

    seq = Sequence(width=64, height=32, frames=(WhiteFrame(), BlackFrame()))
    path = write_manifest(tmp_path / "scan.yaml", seq, ["cam0"], images={"cam0": ["w.png", "b.png"]})
    old = path.read_bytes()
    monkeypatch.setattr(atomic_write, "open", _DiskFullAfter(0), raising=False)
    bigger = Sequence(width=128, height=64, frames=(WhiteFrame(), BlackFrame()))
    with pytest.raises(OutputError, match="No space left on device"):
        write_manifest(path, bigger, ["cam0"], images={"cam0": ["w2.png", "b2.png"]})
    assert path.read_bytes() == old and [p.name for p in tmp_path.iterdir()] == ["scan.yaml"]
    monkeypatch.undo()
    assert read_manifest(path).sequence.width == 64


def _cli(argv: list[str]) -> tuple[int, str]:
    import contextlib
    import io

    from appliance import cli

    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = cli.main(argv)
    return rc, err.getvalue()


RIG = """
sequence: {kind: gray_phase, axes: x, periods_px: [16]}
virtual_rig:
  projector: {width: 160, height: 100, focal_px: 220, position_mm: [60, 0, 0], look_at_mm: [0, 0, 600]}
  cameras:
    cam0: {width: 120, height: 96, focal_px: 180, position_mm: [0, 0, 0], look_at_mm: [0, 0, 600]}
"""


@pytest.mark.parametrize("command", ["patterns", "grab"])
def test_patterns_and_grab_on_a_full_disk_keep_the_previous_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                  command: str) -> None:
    """``scan3d patterns`` / ``scan3d grab`` run twice into one folder, the disk full on the second run's third
    file: one line, exit 2, and the first run's files all as they were (none half-written or replaced)."""
    from appliance import atomic_write

    config = tmp_path / "rig.yaml"
    config.write_text(RIG)
    out = tmp_path / "out"
    if command == "patterns":
        first = ["patterns", "--config", str(config), "--out", str(out), "--width", "64", "--height", "40"]
        second = [*first[:-4], "--width", "96", "--height", "48"]
    else:
        first = ["grab", "--config", str(config), "--camera", "cam0", "--frames", "4", "--out", str(out)]
        second = [*first[:-3], "5", "--out", str(out)]
    rc, err = _cli(first)
    assert rc == 0, err
    before = _snapshot(out)
    assert len(before) >= 4
    monkeypatch.setattr(atomic_write, "open", _DiskFullAfter(2), raising=False)
    rc, err = _cli(second)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert "No space left on device" in lines[0] and str(out) in lines[0], lines[0]
    assert _snapshot(out) == before
    monkeypatch.undo()
    rc, err = _cli(second)  # with room again, the second run replaces the set
    assert rc == 0 and _snapshot(out) != before, err
