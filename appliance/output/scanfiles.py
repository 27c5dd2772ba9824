"""The three files of one scan: cloud (PLY), sidecar (JSON) and preview (PNG)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path

from appliance.output.ply import write_ply
from appliance.output.preview import write_preview
from appliance.output.sidecar import ScanMetadata, write_sidecar
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


def make_scan_id(serial: str, counter: int, when: dt.datetime | None = None) -> str:
    """``YYYYmmdd-HHMMSS-<serial>-<counter>`` (UTC), unique per appliance."""
    when = when or dt.datetime.now(dt.UTC)
    return f"{when:%Y%m%d-%H%M%S}-{serial}-{counter:06d}"


def write_scan_files(
    folder: Path,
    meta: ScanMetadata,
    cloud: PointCloud,
    shapes: list[tuple[int, int]],
    *,
    normals: bool = False,
    preview: bool = True,
) -> ScanFiles:
    """Write cloud, preview and sidecar (in that order, each atomically) into ``folder``.

    The sidecar comes last, so a watcher that keys on ``.json`` finds the cloud complete.
    """
    folder.mkdir(parents=True, exist_ok=True)
    cloud_path = folder / f"{meta.scan_id}.ply"
    preview_path = folder / f"{meta.scan_id}.png" if preview else None
    sidecar_path = folder / f"{meta.scan_id}.json"
    write_ply(cloud_path, cloud, normals=normals, comments=[f"scan3d scan {meta.scan_id}", "units mm"])
    if preview_path is not None:
        write_preview(preview_path, cloud, shapes, title=meta.scan_id)
    meta.files = {"cloud": cloud_path.name, "sidecar": sidecar_path.name}
    if preview_path is not None:
        meta.files["preview"] = preview_path.name
    write_sidecar(sidecar_path, meta)
    return ScanFiles(cloud_path, sidecar_path, preview_path)
