"""The atomic writer loses nothing (issue 28): a writer that fails, a full disk or a NUL in the name leave
the old file whole and no temporary file behind."""

from __future__ import annotations

import errno
from pathlib import Path
from typing import BinaryIO

import pytest

from appliance.errors import OutputError
from appliance.output.atomic import write_atomic, write_bytes_atomic


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
