"""Binary little-endian PLY writing (and a small reader for round trips)."""

from __future__ import annotations

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


def cloud_to_records(cloud: PointCloud, *, camera_field: bool, normals: bool) -> npt.NDArray[np.void]:
    """Pack a cloud into PLY vertex records (structured array, little endian)."""
    if normals and cloud.normal is None:
        raise OutputError("PLY: normals requested but the cloud has none; enable reconstruction.normals")
    dt = _vertex_dtype(cloud, camera_field, normals)
    rec = np.empty(len(cloud), dtype=dt)
    rec["x"], rec["y"], rec["z"] = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    if normals:
        assert cloud.normal is not None
        rec["nx"], rec["ny"], rec["nz"] = cloud.normal[:, 0], cloud.normal[:, 1], cloud.normal[:, 2]
    rec["row"], rec["col"] = cloud.row, cloud.col
    if camera_field:
        rec["camera"] = cloud.camera
    rec["intensity"] = cloud.intensity
    rec["quality"] = cloud.quality
    rec["sigma_mm"] = np.nan if cloud.sigma_mm is None else cloud.sigma_mm
    return rec


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
