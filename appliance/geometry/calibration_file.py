"""The calibration file: OpenCV FileStorage YAML, one top-level map per device.

Layout (every device named as in the configuration, the first camera is the world frame)::

    %YAML:1.0
    ---
    cam0:
       K: !!opencv-matrix {rows: 3, cols: 3, dt: d, data: [...]}   # camera matrix (px)
       dist: !!opencv-matrix {rows: 1, cols: N, ...}                # OpenCV order k1 k2 p1 p2 [k3 ...]
       size: [ 2448, 2048 ]                                         # [width, height] (px)
       R: !!opencv-matrix {rows: 3, cols: 3, ...}                   # x_device = R x_world + T
       T: !!opencv-matrix {rows: 3, cols: 1, ...}                   # (mm)
       rms: 0.12                                                    # reprojection RMS (px)
    projector:
       ...

``cv2.FileStorage(path, cv2.FILE_STORAGE_READ)`` reads it (OpenCV 4 and 5).
"""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from appliance.config.yamlfile import duplicate_key_in, read_text_file
from appliance.errors import CalibrationError
from appliance.geometry.camera import CameraModel

PROJECTOR_NAME = "projector"
"""The device name of the projector in the calibration file and the configuration."""

_HEADER = "%YAML:1.0"

MAX_CALIBRATION_BYTES = 16 * 1024 * 1024
"""Largest calibration file read (bytes)."""


@dataclass
class Calibration:
    """Every calibrated device of the rig.

    Attributes
    ----------
    devices : dict of str to CameraModel
        Devices in file (and configuration) order; the first camera's frame is the world frame.
    """

    devices: dict[str, CameraModel] = field(default_factory=dict)

    @property
    def camera_names(self) -> list[str]:
        """Names of the cameras (every device but the projector), in order."""
        return [n for n in self.devices if n != PROJECTOR_NAME]

    @property
    def cameras(self) -> list[CameraModel]:
        """The camera models, in order."""
        return [self.devices[n] for n in self.camera_names]

    @property
    def projector(self) -> CameraModel | None:
        """The projector model, or None when the calibration has none."""
        return self.devices.get(PROJECTOR_NAME)

    def hash(self) -> str:
        """Short hex digest (16 hex of SHA-256) of the canonical content: names, K, dist, size, R, T, rms."""
        h = hashlib.sha256()
        for name, dev in self.devices.items():
            h.update(name.encode() + b"\0")
            h.update(np.asarray([dev.width, dev.height], "<i8").tobytes())
            for arr in (dev.K, dev.dist, dev.R, dev.T, np.array([dev.rms])):
                a = np.asarray(arr, "<f8").ravel()
                h.update(len(a).to_bytes(4, "little") + np.where(np.isnan(a), np.nan, a + 0.0).tobytes())
        return h.hexdigest()[:16]


def write_calibration(path: str | os.PathLike[str], calib: Calibration) -> None:
    """Write a calibration file atomically (temporary file, fsync, rename).

    Parameters
    ----------
    path : path-like
        Destination (``.yaml``); its folder must exist.
    calib : Calibration
        The devices to write, in order.

    Raises
    ------
    CalibrationError
        When a device name is not a valid key or the file cannot be written.
    """
    import cv2

    path = Path(path)
    if not calib.devices:
        raise CalibrationError(f"{path}: calibration has no devices: nothing to write")
    for name in calib.devices:
        if (
            not name
            or not (name[0].isalpha() or name[0] == "_")
            or not all(c.isalnum() or c in "_-" for c in name)
        ):
            raise CalibrationError(
                f"{path}: device name {name!r}: must start with a letter and hold only [A-Za-z0-9_-]"
            )
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.yaml")
    try:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
        if not fs.isOpened():
            raise CalibrationError(
                f"{path}: cannot open {tmp} for writing; check the folder exists and is writable"
            )
        for name, dev in calib.devices.items():
            fs.startWriteStruct(name, cv2.FileNode_MAP)
            fs.write("K", np.ascontiguousarray(dev.K, np.float64))
            dist = dev.dist if dev.dist.size else np.zeros(5)  # "no distortion" is written as five zeros
            fs.write("dist", np.ascontiguousarray(dist, np.float64).reshape(1, -1))
            fs.startWriteStruct("size", cv2.FileNode_SEQ | cv2.FileNode_FLOW)
            fs.write("", int(dev.width))
            fs.write("", int(dev.height))
            fs.endWriteStruct()
            fs.write("R", np.ascontiguousarray(dev.R, np.float64))
            fs.write("T", np.ascontiguousarray(dev.T, np.float64).reshape(3, 1))
            fs.write("rms", float(dev.rms))
            fs.endWriteStruct()
        fs.release()
        text = tmp.read_text()
        # OpenCV 5 writes "%YAML 1.2"; "%YAML:1.0" is what OpenCV 4 writes and both versions read
        lines = text.split("\n", 1)
        if lines[0].startswith("%YAML"):
            text = _HEADER + "\n" + (lines[1] if len(lines) > 1 else "")
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError as e:
        raise CalibrationError(f"{path}: cannot write calibration ({e.strerror or e}); check the folder exists, "
                               "is writable and has free space") from e
    except cv2.error as e:  # OpenCV's own writer failing (a full disk, a folder that vanished)
        raise CalibrationError(f"{path}: cannot write calibration ({str(e).strip()[-120:]}); check the folder "
                               "exists, is writable and has free space") from e
    finally:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:  # a read-only folder holds no temporary file; its error must not hide the real one
            pass


def read_calibration(
    path: str | os.PathLike[str], projector_size: tuple[int, int] | None = None
) -> Calibration:
    """Read a calibration file with ``cv2.FileStorage``.

    Besides this project's layout, the flat ``caliInfo.yml`` layouts of SLMaster are imported, chosen by
    the keys present (see :func:`read_slmaster`).

    Parameters
    ----------
    path : path-like
        The YAML file (see the module docstring for its layout).
    projector_size : (width, height), optional
        Projector size (px) for layouts that do not store it (SLMaster's monocular file); a scan
        manifest's ``projector`` entry gives it.

    Returns
    -------
    Calibration
        Devices in file order.

    Raises
    ------
    CalibrationError
        Naming the file, the device and the key on any problem (missing, unparsable, wrong shape, not finite,
        R not a rotation, ...).
    """
    import cv2

    path = Path(path)
    if not path.exists():
        raise CalibrationError(f"{path}: calibration file not found; run the calibration or fix the path")
    # a regular file of sane size only (a FIFO or a device would block or never end); OpenCV parses the text
    text = read_text_file(path, what="calibration", error=CalibrationError, limit_bytes=MAX_CALIBRATION_BYTES,
                          fix="run the calibration or fix the path")
    twice = _duplicate_key(text)
    if twice is not None:  # OpenCV keeps one of the two silently
        raise CalibrationError(f"{path}:{twice[2]}: {twice[0]!r} is given twice (lines {twice[1]} and {twice[2]}); "
                               "a calibration states each device and value once, so remove one")
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except Exception as e:  # cv2.error, or SystemError wrapping it
        cause = e.__cause__ or e
        raise CalibrationError(
            f"{path}: not an OpenCV FileStorage YAML file: {' '.join(str(cause).split())[-200:]}"
        ) from e
    if not fs.isOpened():
        raise CalibrationError(f"{path}: cannot be opened by cv2.FileStorage")
    try:
        root = fs.root()
        if not root.isMap():
            raise CalibrationError(f"{path}: holds no device maps (cam0:, projector:, ...): the file is empty or "
                                   "not a calibration; run the calibration or restore the file")
        keys = set(root.keys())
        if SLMASTER_CAMERA_KEYS <= keys:
            return read_slmaster(path, root, projector_size)
        devices: dict[str, CameraModel] = {}
        for name in root.keys():
            node = root.getNode(name)
            if not node.isMap():
                continue  # other top-level entries (comments, dates) are not devices
            devices[name] = _read_device(path, name, node)
    except cv2.error as e:  # OpenCV asserts on shapes it did not expect
        raise CalibrationError(f"{path}: not a calibration OpenCV can read: {' '.join(str(e).split())[-160:]}") from e
    finally:
        fs.release()
    if not devices:
        raise CalibrationError(f"{path}: no device maps (cam0:, projector:, ...) at the top level")
    proj = devices.get(PROJECTOR_NAME)
    if proj is not None and projector_size is not None and (proj.width, proj.height) != tuple(projector_size):
        w, h = projector_size
        raise CalibrationError(f"{path}: the projector is calibrated at {proj.width}x{proj.height} but the capture's "
                               f"projector is {w}x{h}; use the calibration of this projector (or fix the manifest's "
                               "projector size)")
    if all(n == PROJECTOR_NAME for n in devices):
        raise CalibrationError(f"{path}: holds only the projector: at least one camera is needed")
    return Calibration(devices)


def _duplicate_key(text: str) -> tuple[str, int, int] | None:
    """The first key given twice in one mapping of an OpenCV YAML text: (key, first line, second line)."""
    import yaml

    if text.startswith("%YAML"):  # OpenCV's "%YAML:1.0" is no YAML directive; keep the line numbers
        text = "\n" + text.split("\n", 1)[-1] if "\n" in text else ""
    try:
        root = yaml.compose(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except (yaml.YAMLError, RecursionError):
        return None  # not YAML that PyYAML reads: OpenCV judges it
    return duplicate_key_in(root)


def _numbers(path: Path, name: str, key: str, node: Any) -> npt.NDArray[np.float64]:
    """A node's values as float64: an opencv-matrix, a sequence or a number."""
    where = f"{path}: {name}.{key}"
    if node.empty() or node.isNone():
        raise CalibrationError(f"{where}: missing; every device needs K, dist, size, R, T")
    if node.isMap():  # an opencv-matrix: 8/16-bit types would have saturated the values
        dt = node.getNode("dt").string() if not node.getNode("dt").empty() else "?"
        if dt not in ("d", "f", "i"):
            raise CalibrationError(f"{where}: matrix type dt: {dt}: must be d (float64) or f (float32); a "
                                   "calibration's values do not fit small integer types")
    elif node.isString():
        raise CalibrationError(f"{where}: {node.string()!r}: must be a number or a matrix")
    try:
        if node.isSeq():
            vals = [node.at(i).real() for i in range(node.size())]
            arr = np.asarray(vals, np.float64)
        elif node.isReal() or node.isInt():
            arr = np.asarray([node.real()], np.float64)
        else:
            mat = node.mat()
            if mat is None:
                raise CalibrationError(f"{where}: not a matrix, sequence or number")
            arr = np.asarray(mat, np.float64)
    except CalibrationError:
        raise
    except Exception as e:  # OpenCV's messages span lines
        raise CalibrationError(f"{where}: unreadable ({' '.join(str(e).split())[-200:]}); check its rows, cols, dt "
                               "and data") from e
    return arr


def _read_device(path: Path, name: str, node: Any) -> CameraModel:
    def get(
        key: str, shape: tuple[int, ...] | None, sizes: tuple[int, ...] | None = None
    ) -> npt.NDArray[np.float64]:
        arr = _numbers(path, name, key, node.getNode(key))
        if shape is not None and arr.size != int(np.prod(shape)):
            raise CalibrationError(
                f"{path}: {name}.{key}: has {arr.size} values, shape {arr.shape}: must be {shape}"
            )
        if sizes is not None and arr.size not in sizes:
            raise CalibrationError(
                f"{path}: {name}.{key}: has {arr.size} values: must be one of {sizes} (OpenCV order)"
            )
        if not np.all(np.isfinite(arr)):
            raise CalibrationError(f"{path}: {name}.{key}: holds non-finite values {arr.ravel().tolist()}")
        return arr.reshape(shape) if shape is not None else arr.ravel()

    k = get("K", (3, 3))
    if not (k[0, 0] > 0 and k[1, 1] > 0 and np.allclose(k[2], [0, 0, 1]) and k[1, 0] == 0):
        raise CalibrationError(
            f"{path}: {name}.K: {k.tolist()}: must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0"
        )
    dist = get("dist", None, (4, 5, 8, 12, 14))
    size = get("size", (2,))
    if not (size[0] >= 1 and size[1] >= 1 and np.all(size == np.round(size))):
        raise CalibrationError(
            f"{path}: {name}.size: {size.tolist()}: must be [width, height], positive integers (px)"
        )
    r = get("R", (3, 3))
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise CalibrationError(f"{path}: {name}.R: not a rotation matrix (R R^T != I or det < 0)")
    t = get("T", (3,))
    rms_node = node.getNode("rms")
    if rms_node.empty() or rms_node.isNone():
        rms = float("nan")
    elif not (rms_node.isReal() or rms_node.isInt()) or not (
            math.isnan(rms_node.real()) or 0 <= rms_node.real() < 1e6):  # NaN: not stated
        shown = rms_node.string() if rms_node.isString() else rms_node.real()
        raise CalibrationError(f"{path}: {name}.rms = {shown!r}: must be a number >= 0 (px) or absent")
    else:
        rms = float(rms_node.real())
    try:
        return CameraModel(name, k, dist, int(size[0]), int(size[1]), r, t, rms)
    except CalibrationError as e:
        raise CalibrationError(f"{path}: {e}") from e


# --------------------------------------------------------------------------------------------------
# SLMaster caliInfo.yml (flat matrices; imported, never written)
# --------------------------------------------------------------------------------------------------

SLMASTER_CAMERA_KEYS = frozenset({"M1", "D1", "S"})
"""Top-level keys that mark SLMaster's flat ``caliInfo.yml`` layout."""
SLMASTER_NAMES = ("L", "R")
"""Device names given to SLMaster's left (reference) and right cameras; the projector is ``projector``."""


def read_slmaster(path: Path, root: Any, projector_size: tuple[int, int] | None = None) -> Calibration:
    """Import an SLMaster ``caliInfo.yml`` (an open ``cv2.FileStorage`` root).

    Layouts (lengths in mm; ``S`` = [width, height] of the cameras):

    * monocular: ``M1, D1`` (camera ``L``), ``M4, D4`` (projector), ``Rlp, Tlp`` with
      ``X_P = Rlp X_C + Tlp``. The projector size is not stored: ``projector_size`` gives it.
    * binocular: ``M1, D1`` (camera ``L``), ``M2, D2`` (camera ``R``), ``Rlr, Tlr`` with
      ``X_R = Rlr X_L + Tlr``. Rectification entries (``R1, P1, ...``) are not needed and ignored.

    The left camera is the world frame. Reprojection RMS is not stored (NaN).

    Raises
    ------
    CalibrationError
        Naming the file and the key when an entry is missing or malformed.
    """
    keys = set(root.keys())

    def mat(key: str, shape: tuple[int, ...] | None) -> npt.NDArray[np.float64]:
        arr = _numbers(path, "caliInfo", key, root.getNode(key))
        if shape is not None and arr.size != int(np.prod(shape)):
            raise CalibrationError(f"{path}: {key}: has {arr.size} values: must be {shape} (SLMaster layout)")
        if not np.all(np.isfinite(arr)):
            raise CalibrationError(f"{path}: {key}: holds non-finite values {arr.ravel().tolist()}")
        return arr.reshape(shape) if shape is not None else arr.ravel()

    size = mat("S", (2,))
    w, h = round(float(size[0])), round(float(size[1]))

    def device(name: str, k: str, d: str, width: int, height: int,
               r: npt.NDArray[np.float64] | None = None, t: npt.NDArray[np.float64] | None = None) -> CameraModel:
        if r is not None and (not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0):
            raise CalibrationError(f"{path}: the rotation of {name} is not a rotation matrix (R R^T != I)")
        dist = mat(d, None)
        try:
            return CameraModel(name, mat(k, (3, 3)), dist, width, height,
                               np.eye(3) if r is None else r, np.zeros(3) if t is None else t)
        except CalibrationError as e:
            raise CalibrationError(f"{path}: {e}") from e

    devices = {SLMASTER_NAMES[0]: device(SLMASTER_NAMES[0], "M1", "D1", w, h)}
    if {"M2", "D2", "Rlr", "Tlr"} <= keys:
        devices[SLMASTER_NAMES[1]] = device(SLMASTER_NAMES[1], "M2", "D2", w, h, mat("Rlr", (3, 3)), mat("Tlr", (3,)))
    if {"M4", "D4", "Rlp", "Tlp"} <= keys:
        if projector_size is None:
            raise CalibrationError(
                f"{path}: SLMaster layout with a projector (M4, Rlp, Tlp) but no projector size: the file does "
                "not store it; give it (the scan manifest's projector entry, e.g. 1920x1080 for a DLP4710)"
            )
        pw, ph = (int(v) for v in projector_size)
        devices[PROJECTOR_NAME] = device(PROJECTOR_NAME, "M4", "D4", pw, ph, mat("Rlp", (3, 3)), mat("Tlp", (3,)))
    if len(devices) == 1:
        raise CalibrationError(
            f"{path}: SLMaster layout with camera M1 only: needs M2, D2, Rlr, Tlr (second camera) or M4, D4, "
            "Rlp, Tlp (projector)"
        )
    return Calibration(devices)
