"""The three files of one scan: cloud (PLY), sidecar (JSON) and preview (PNG).

:func:`scan_file_contents` renders them in memory (the PLY as its header and its records, packed from the cloud
a chunk at a time while written), so the share writer can put them on the share through its deadlines;
:func:`write_scan_files` writes them into a local folder.
"""

from __future__ import annotations

import datetime as dt
import hashlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
import numpy.typing as npt

from appliance.output.atomic import write_atomic
from appliance.output.ply import PackedRecords, ply_bytes_header, vertex_dtype
from appliance.output.png import encode_png
from appliance.output.preview import depth_image, render_preview
from appliance.output.sidecar import ScanMetadata
from appliance.reconstruct.types import PointCloud


@dataclass(frozen=True)
class ScanFiles:
    """Paths of the files of one scan."""

    cloud: Path
    sidecar: Path
    preview: Path | None

    def all(self) -> list[Path]:
        """Every path, cloud first, sidecar last."""
        return [p for p in (self.cloud, self.preview, self.sidecar) if p is not None]


@dataclass(frozen=True)
class FileContent:
    """One file of a scan, rendered: its name and its bytes in pieces (written one after the other).

    A piece is bytes, or a cloud's PLY records packed a chunk at a time while they are written
    (:class:`appliance.output.ply.PackedRecords`).
    """

    name: str
    pieces: tuple[bytes | memoryview | PackedRecords, ...]

    @property
    def size(self) -> int:
        """Length of the file (bytes)."""
        return sum(p.nbytes if isinstance(p, PackedRecords) else memoryview(p).nbytes for p in self.pieces)

    def chunks(self) -> Iterator[memoryview]:
        """The content in order, as byte views of at most a few MB each (a PLY's records are packed here)."""
        for p in self.pieces:
            if isinstance(p, PackedRecords):
                yield from p
            else:
                yield memoryview(p).cast("B")

    def sha256(self) -> str:
        """Hex SHA-256 of the content."""
        h = hashlib.sha256()
        for c in self.chunks():
            h.update(c)
        return h.hexdigest()

    def write_to(self, f: BinaryIO) -> None:
        """Write the pieces into the open binary file ``f``."""
        for c in self.chunks():
            f.write(c)


def make_scan_id(serial: str, counter: int, when: dt.datetime | None = None) -> str:
    """``YYYYmmdd-HHMMSS-<serial>-<counter>`` (UTC), unique per appliance."""
    when = when or dt.datetime.now(dt.UTC)
    return f"{when:%Y%m%d-%H%M%S}-{serial}-{counter:06d}"


def scan_file_contents(
    meta: ScanMetadata,
    cloud: PointCloud,
    shapes: list[tuple[int, int]],
    *,
    normals: bool = False,
    preview: bool = True,
    comments: list[str] | None = None,
    reasons: list[npt.NDArray[np.uint8] | None] | None = None,
) -> list[FileContent]:
    """Render the files of one scan in memory: cloud, preview (when ``preview``), sidecar last.

    Parameters
    ----------
    meta : ScanMetadata
        The sidecar's content; its ``files`` is filled in here.
    cloud : PointCloud
        The points (N of them, mm, world frame).
    shapes : list of (int, int)
        (H, W) of each camera (px), for the preview's tiles.
    normals, preview : bool
        Normals in the PLY; a preview PNG.
    comments : list of str, optional
        The PLY header's comments (default: the scan id and ``units mm``).
    reasons : list of (ndarray, shape (H, W), uint8, or None), optional
        Per camera (order of ``shapes``), why each pixel has no point
        (:class:`appliance.reconstruct.types.Reason`): drawn in the preview with a legend
        (:func:`appliance.output.preview.render_preview`).

    Returns
    -------
    list of FileContent
        ``<scan-id>.ply``, ``<scan-id>.png`` (optional) and ``<scan-id>.json``, in that order. The PLY's
        records are packed from the cloud a chunk at a time while written, never as one full copy.
    """
    sid = meta.scan_id
    camera_field = bool(len(cloud)) and bool((cloud.camera != cloud.camera[0]).any())
    dtype = vertex_dtype(cloud, camera_field=camera_field, normals=normals)
    header = ply_bytes_header(cloud, dtype, [f"scan3d scan {sid}", "units mm"] if comments is None else comments)
    out = [FileContent(f"{sid}.ply", (header, PackedRecords(cloud, dtype)))]
    meta.files = {"cloud": f"{sid}.ply", "sidecar": f"{sid}.json"}
    if preview:
        depths = [depth_image(cloud, i, s) for i, s in enumerate(shapes)]
        out.append(FileContent(f"{sid}.png", (encode_png(render_preview(depths, sid, reasons=reasons)),)))
        meta.files["preview"] = f"{sid}.png"
    out.append(FileContent(f"{sid}.json", (meta.to_json().encode(),)))
    return out


def write_scan_files(
    folder: Path,
    meta: ScanMetadata,
    cloud: PointCloud,
    shapes: list[tuple[int, int]],
    *,
    normals: bool = False,
    preview: bool = True,
) -> ScanFiles:
    """Write cloud, preview and sidecar (in that order, each atomically) into the local ``folder``.

    The sidecar comes last, so a watcher that keys on ``.json`` finds the cloud complete.
    """
    folder.mkdir(parents=True, exist_ok=True)
    contents = scan_file_contents(meta, cloud, shapes, normals=normals, preview=preview)
    paths = [write_atomic(folder / c.name, c.write_to) for c in contents]
    return ScanFiles(paths[0], paths[-1], paths[1] if preview else None)
