"""Binary little-endian PLY writing (and a small reader for round trips)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np
import numpy.typing as npt

from appliance.errors import OutputError
from appliance.output.atomic import write_atomic
from appliance.reconstruct.types import PointCloud


def _vertex_dtype(cloud: PointCloud, with_camera: bool, with_normals: bool) -> np.dtype[np.void]:
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if with_normals:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    fields += [("row", "<u2"), ("col", "<u2")]
    if with_camera:
        fields.append(("camera", "u1"))
    fields += [("intensity", "u1"), ("quality", "<f4"), ("sigma_mm", "<f4")]
    return np.dtype(fields)


_PLY_TYPES = {"<f4": "float", "<u2": "ushort", "u1": "uchar", "|u1": "uchar"}


def ply_bytes_header(cloud: PointCloud, dtype: np.dtype[np.void], comments: list[str]) -> bytes:
    """The PLY header for ``cloud`` with vertex layout ``dtype``."""
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element vertex {len(cloud)}")
    for name in dtype.names or ():
        lines.append(f"property {_PLY_TYPES[dtype[name].str]} {name}")
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def vertex_dtype(cloud: PointCloud, *, camera_field: bool, normals: bool) -> np.dtype[np.void]:
    """The PLY vertex record layout of ``cloud`` (checks that requested normals exist)."""
    if normals and cloud.normal is None:
        raise OutputError("PLY: normals requested but the cloud has none; enable reconstruction.normals")
    return _vertex_dtype(cloud, camera_field, normals)


def _pack(cloud: PointCloud, dt: np.dtype[np.void], start: int, stop: int) -> npt.NDArray[np.void]:
    rec = np.empty(stop - start, dtype=dt)
    s = slice(start, stop)
    rec["x"], rec["y"], rec["z"] = cloud.xyz[s, 0], cloud.xyz[s, 1], cloud.xyz[s, 2]
    names = dt.names or ()
    if "nx" in names:
        assert cloud.normal is not None
        rec["nx"], rec["ny"], rec["nz"] = cloud.normal[s, 0], cloud.normal[s, 1], cloud.normal[s, 2]
    rec["row"], rec["col"] = cloud.row[s], cloud.col[s]
    if "camera" in names:
        rec["camera"] = cloud.camera[s]
    rec["intensity"] = cloud.intensity[s]
    rec["quality"] = cloud.quality[s]
    rec["sigma_mm"] = np.nan if cloud.sigma_mm is None else cloud.sigma_mm[s]
    return rec


def cloud_to_records(cloud: PointCloud, *, camera_field: bool, normals: bool) -> npt.NDArray[np.void]:
    """Pack a cloud into PLY vertex records (structured array, little endian)."""
    dt = vertex_dtype(cloud, camera_field=camera_field, normals=normals)
    return _pack(cloud, dt, 0, len(cloud))


class PackedRecords:
    """A cloud's PLY vertex records, packed :data:`RECORDS_PER_CHUNK` points at a time when iterated.

    Stands for the records' bytes without a full packed copy of the cloud (~25 bytes a point, 31 MB for
    1.25 M points) being held while a scan's files are written; it keeps a reference to the cloud, so
    pooled cloud buffers stay leased until the file is written.

    Parameters
    ----------
    cloud : PointCloud
        The points (N of them).
    dtype : numpy.dtype
        Record layout (:func:`vertex_dtype`).
    """

    def __init__(self, cloud: PointCloud, dtype: np.dtype[np.void]) -> None:
        self.cloud = cloud
        self.dtype = dtype

    @property
    def nbytes(self) -> int:
        """Length of the records (bytes): N times the record size."""
        return len(self.cloud) * self.dtype.itemsize

    def __iter__(self) -> Iterator[memoryview]:
        n = len(self.cloud)
        for start in range(0, n, RECORDS_PER_CHUNK):
            yield _pack(self.cloud, self.dtype, start, min(n, start + RECORDS_PER_CHUNK)).data.cast("B")


RECORDS_PER_CHUNK = 1 << 17
"""Points packed at a time by :class:`PackedRecords` (about 3 MB of records)."""


def write_ply(
    path: str | Path,
    cloud: PointCloud,
    *,
    normals: bool = False,
    camera_field: bool | None = None,
    comments: list[str] | None = None,
) -> Path:
    """Write ``cloud`` as a binary little-endian PLY, atomically.

    Vertex properties: ``x y z`` (float32, mm, world frame), ``nx ny nz`` (with ``normals``),
    ``row col`` (ushort, camera pixel), ``camera`` (uchar, when several cameras contributed or
    ``camera_field``), ``intensity`` (uchar), ``quality`` (float32), ``sigma_mm`` (float32: expected 1-sigma
    error along the camera ray, mm; NaN where unknown).

    Parameters
    ----------
    path : path-like
        Output file.
    cloud : PointCloud
        Points (N of them).
    normals : bool
        Write normals (the cloud must have them).
    camera_field : bool, optional
        Force the ``camera`` property on or off (default: on when more than one camera index occurs).
    comments : list of str, optional
        Header comments (one line each).
    """
    path = Path(path)
    if camera_field is None:
        camera_field = bool(len(cloud)) and bool(np.any(cloud.camera != cloud.camera[0]))
    rec = cloud_to_records(cloud, camera_field=camera_field, normals=normals)
    header = ply_bytes_header(cloud, rec.dtype, comments or [])

    def _write(f: BinaryIO) -> None:
        f.write(header)
        f.write(rec.data.cast("B"))  # the records' own bytes, no copy

    return write_atomic(path, _write)


def read_ply_vertices(path: str | Path) -> npt.NDArray[np.void]:
    """Read the vertex records of a binary little-endian PLY written by :func:`write_ply`."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise OutputError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise OutputError(f"{path}: only binary_little_endian PLY is supported")
    fields: list[tuple[str, str]] = []
    count = 0
    rev = {"float": "<f4", "ushort": "<u2", "uchar": "u1"}
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            count = int(parts[2])
        elif parts and parts[0] == "property":
            fields.append((parts[2], rev[parts[1]]))
    return np.frombuffer(data, dtype=np.dtype(fields), count=count, offset=end + len(b"end_header\n"))
