"""Reading and writing scan manifests (``SEQUENCE-MANIFEST.md``).

A manifest is YAML: the projector size, the camera names and, in capture order, each frame's pattern
with either one image per camera (``images``) or, for the whole manifest, one ``.npy`` stack per camera
(``stacks``). Paths are relative to the manifest's folder.
"""

from __future__ import annotations

import math
import os
import stat
from collections.abc import Callable, Mapping
from collections.abc import Sequence as Sequence_
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml

from appliance.atomic_write import write_bytes_atomic
from appliance.config.yamlfile import DuplicateKeyError, parse_yaml, read_bytes_file, read_text_file, yaml_problem
from appliance.errors import ManifestError, PatternError
from appliance.patterns.sequence import (
    BlackFrame,
    Frame,
    GrayFrame,
    OtherFrame,
    PhaseFrame,
    Sequence,
    WhiteFrame,
)

FrameStack = npt.NDArray[np.uint8] | npt.NDArray[np.uint16]

MAX_MANIFEST_BYTES = 4 * 1024 * 1024
"""Largest manifest read (bytes): some 20 000 frames."""


@dataclass(frozen=True)
class Manifest:
    """A captured sequence: the frames' patterns and where each camera's images are.

    Attributes
    ----------
    path : Path
        The manifest file; relative image paths are resolved against its folder.
    sequence : Sequence
        The frames, in capture order.
    cameras : tuple of str
        Camera names, as in the calibration file.
    images : dict or None
        ``images[camera][i]``: the image of frame ``i`` (absolute path).
    stacks : dict or None
        ``stacks[camera]``: a ``.npy`` array (frames, height, width) (absolute path).
    bit_depth : int or None
        Significant bits of the pixel values (8..16); None: the data type's own (8 for uint8, 16 for uint16).
    exposures : tuple of (float, float) or None
        Per frame its ``(exposure_us, intensity)`` when any frame states either (a high-dynamic-range capture:
        the same patterns at several exposures or projector intensities); None: one exposure for all.
    """

    path: Path
    sequence: Sequence
    cameras: tuple[str, ...]
    images: dict[str, tuple[Path, ...]] | None = None
    stacks: dict[str, Path] | None = None
    bit_depth: int | None = None
    exposures: tuple[tuple[float, float], ...] | None = None

    def bits_of(self, stack: FrameStack) -> int:
        """Significant bits of ``stack`` (this manifest's ``bit_depth``, else its dtype's)."""
        if self.bit_depth is not None:
            return self.bit_depth
        return 8 if stack.dtype == np.uint8 else 16

    def load_stack(self, camera: str) -> FrameStack:
        """Load every frame of ``camera`` as one array.

        Returns
        -------
        ndarray, shape (frames, height, width), uint8 or uint16
        """
        if camera not in self.cameras:
            raise ManifestError(
                f"{self.path}: camera {camera!r} is not in this manifest (it has {list(self.cameras)})"
            )
        if self.stacks is not None:
            stack = _load_npy(self.stacks[camera], len(self.sequence), self.path)
        else:
            assert self.images is not None
            stack = load_images(self.images[camera], self.path)
        check_bit_depth(stack, self.bits_of(stack), f"{self.path}: camera {camera!r}")
        return stack


def check_bit_depth(stack: FrameStack, bits: int, where: str) -> None:
    """Refuse a stack whose values do not fit ``bits`` significant bits, or whose dtype cannot hold them.

    Raises
    ------
    ManifestError
        Naming ``where``, the bit depth, the offending value and frame, and the fix.
    """
    if stack.dtype == np.uint8:
        if bits != 8:
            raise ManifestError(
                f"{where}: bit_depth = {bits} but the frames are 8-bit (uint8); remove bit_depth or store the "
                "frames as 16-bit images"
            )
        return
    if bits >= 16:
        return
    top = (1 << bits) - 1
    peaks = stack.reshape(stack.shape[0], -1).max(axis=1)
    bad = np.flatnonzero(peaks > top)
    if bad.size:
        i = int(bad[0])
        raise ManifestError(
            f"{where}: bit_depth = {bits} but frame {i} holds the value {int(peaks[i])} (> {top}, the largest "
            f"{bits}-bit value); give the frames' real bit depth (or none for full 16-bit data) or shift the "
            "values down"
        )


def _load_npy(path: Path, n_frames: int, manifest: Path) -> FrameStack:
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a FIFO or a device would block or never end
            raise ManifestError(f"{manifest}: stack {path}: not a regular file; a stack is a .npy file")
        arr = np.load(path, mmap_mode="r")
    except (OSError, ValueError, EOFError) as exc:  # EOFError: an empty file
        raise ManifestError(f"{manifest}: stack {path}: cannot be read ({exc or type(exc).__name__}); check the "
                            "file") from exc
    if arr.ndim != 3 or arr.shape[0] != n_frames:
        raise ManifestError(
            f"{manifest}: stack {path}: shape {arr.shape}: must be ({n_frames}, height, width), "
            "one image per frame in the manifest"
        )
    if arr.dtype not in (np.uint8, np.uint16):
        raise ManifestError(f"{manifest}: stack {path}: dtype {arr.dtype}: must be uint8 or uint16")
    return np.ascontiguousarray(arr)


def _frame_bytes(p: Path, i: int, manifest: Path | str) -> bytes:
    """One frame file's bytes, checked for a missing file and a JPEG or PNG cut short."""
    if not p.exists():
        raise ManifestError(f"{manifest}: frame {i}: image {p} is missing or unreadable; check the path")
    try:
        data = read_bytes_file(p, what="frame image", error=ManifestError, limit_bytes=MAX_IMAGE_BYTES)
    except ManifestError as exc:
        raise ManifestError(f"{manifest}: frame {i}: {exc}") from exc
    truncated = _truncated(data)
    if truncated:
        raise ManifestError(f"{manifest}: frame {i}: image {p} is truncated ({truncated}); copy the capture again")
    return data


def _read_image(p: Path, i: int, manifest: Path | str) -> npt.NDArray[Any]:
    """One frame as a 2-D 8 or 16 bit array (colour images are converted to grey)."""
    return _decode_image(_frame_bytes(p, i, manifest), p, i, manifest)


def _decode_image(data: bytes, p: Path, i: int, manifest: Path | str) -> npt.NDArray[Any]:
    """Decode one frame file's bytes to a 2-D 8 or 16 bit grey array (OpenCV)."""
    import cv2

    # Decoded straight to grey at the file's bit depth: a colour JPEG then skips its chroma planes (1.4x faster
    # a frame); EXIF orientation is ignored, as the camera wrote the pixels.
    flags = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_IGNORE_ORIENTATION
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    if img is None:
        raise ManifestError(f"{manifest}: frame {i}: image {p} is empty or not an image OpenCV can decode; "
                            "check the file")
    if img.dtype not in (np.uint8, np.uint16):
        raise ManifestError(f"{manifest}: frame {i}: image {p} has dtype {img.dtype}: must be 8 or 16 bit")
    return np.asarray(img)


def _jpeg_into(data: bytes, out: npt.NDArray[Any]) -> bool:
    """Decode an 8-bit JPEG's grey (luma) straight into ``out`` (H, W) uint8; False where it cannot.

    libjpeg-turbo through ``simplejpeg`` (optional): the decoder writes into the stack itself, so a frame is
    neither allocated nor copied (a batch of 1920x1280 frames loads 1.6x faster on two cores than through
    OpenCV). Its grey is the JPEG's own Y plane, as OpenCV's ``IMREAD_GRAYSCALE`` gives it (bit-identical);
    EXIF orientation is ignored, as there. False (the caller then decodes with OpenCV, which names any
    problem) when ``simplejpeg`` is missing, the file is not a JPEG of ``out``'s size, is CMYK, or does not
    decode cleanly.
    """
    if _simplejpeg is None or data[:3] != b"\xff\xd8\xff" or out.dtype != np.uint8 or out.ndim != 2:
        return False
    try:
        h, w, space, _ = _simplejpeg.decode_jpeg_header(data)
        if (h, w) != out.shape or space not in ("Gray", "YCbCr") or not out.flags.c_contiguous:
            return False
        _simplejpeg.decode_jpeg(data, colorspace="GRAY", buffer=out)
    except (ValueError, TypeError, RuntimeError):
        return False
    return True


def _import_simplejpeg() -> Any:
    try:
        import simplejpeg
    except ImportError:  # optional: OpenCV decodes the JPEGs then
        return None
    return simplejpeg


_simplejpeg: Any = _import_simplejpeg()


MAX_IMAGE_BYTES = 1024 * 1024 * 1024
"""Largest frame image file read (bytes)."""


def _truncated(data: bytes) -> str:
    """Why an encoded JPEG or PNG ends early ('' when it looks whole; other formats are left to the decoder)."""
    if data[:3] == b"\xff\xd8\xff" and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        return "a JPEG without its end marker"
    if data[:8] == b"\x89PNG\r\n\x1a\n" and b"IEND" not in data[-16:]:
        return "a PNG without its IEND chunk"
    return ""


def load_images(
    paths: tuple[Path, ...] | list[Path], manifest: Path | str = "manifest", threads: int | None = None
) -> FrameStack:
    """Read grayscale images (PNG, JPEG, TIFF, 8 or 16 bit) into one (frames, height, width) stack.

    The frames are read by ``threads`` threads at once (default: one per CPU core this process may use); the
    image decoders release the GIL, so a batch of JPEGs decodes on every core. 8-bit JPEGs are decoded by
    libjpeg-turbo straight into the stack where ``simplejpeg`` is installed (bit-identical to OpenCV's grey),
    everything else by OpenCV. On a bad frame the error names the first one in capture order.
    """
    if not paths:
        raise ManifestError(f"{manifest}: no frames")
    first = _read_image(Path(paths[0]), 0, manifest)
    out = np.empty((len(paths), *first.shape), dtype=first.dtype)
    out[0] = first

    def read_into(i: int) -> None:
        p = Path(paths[i])
        data = _frame_bytes(p, i, manifest)
        if _jpeg_into(data, out[i]):
            return
        img = _decode_image(data, p, i, manifest)
        if img.shape != first.shape or img.dtype != first.dtype:
            raise ManifestError(
                f"{manifest}: frame {i}: image {paths[i]} is {img.shape[1]}x{img.shape[0]} {img.dtype}, but "
                f"frame 0 is {first.shape[1]}x{first.shape[0]} {first.dtype}: all frames of a camera must match"
            )
        out[i] = img

    n = threads if threads is not None else len(os.sched_getaffinity(0))
    if n <= 1 or len(paths) < 3:
        for i in range(1, len(paths)):
            read_into(i)
        return out
    with ThreadPoolExecutor(min(n, len(paths) - 1), thread_name_prefix="load-images") as pool:
        done = list(pool.map(_outcome(read_into), range(1, len(paths))))
    for exc in done:  # the first bad frame in capture order
        if exc is not None:
            raise exc
    return out


def _outcome(fn: Callable[[int], None]) -> Callable[[int], BaseException | None]:
    """``fn`` made to return its exception instead of raising it (every frame is tried, the first error wins)."""

    def run(i: int) -> BaseException | None:
        try:
            fn(i)
        except ManifestError as exc:
            return exc
        return None

    return run


# --------------------------------------------------------------------------------------------------
# YAML <-> frames
# --------------------------------------------------------------------------------------------------


def frame_to_dict(frame: Frame) -> dict[str, Any]:
    """The manifest mapping of one frame (without ``images``)."""
    if isinstance(frame, GrayFrame):
        d: dict[str, Any] = {"pattern": "gray", "axis": frame.axis, "bit": frame.bit, "inverted": frame.inverted}
        if frame.stripe != 1:
            d["stripe"] = frame.stripe
        if frame.xor_with is not None:
            d["xor_with"] = frame.xor_with
        return d
    if isinstance(frame, PhaseFrame):
        d = {
            "pattern": "phase",
            "axis": frame.axis,
            "period": frame.period,
            "step": frame.step,
            "steps": frame.steps,
        }
        if frame.offset != 0.0:
            d["offset"] = frame.offset
        return d
    if isinstance(frame, WhiteFrame):
        return {"pattern": "white"}
    if isinstance(frame, BlackFrame):
        return {"pattern": "black"}
    return {"pattern": frame.pattern, **dict(frame.params)}


#: Keys any frame may carry (SEQUENCE-MANIFEST.md): its images, the camera exposure and projector intensity.
_ANY_KEYS = {"pattern", "images", "exposure_us", "intensity"}
_GRAY_KEYS = {"axis", "bit", "inverted", "stripe", "xor_with"} | _ANY_KEYS
_PHASE_KEYS = {"axis", "period", "step", "steps", "offset"} | _ANY_KEYS


def frame_from_dict(d: Mapping[str, Any], where: str) -> Frame:
    """Parse one manifest frame mapping; ``where`` names it in error messages."""
    if not isinstance(d, Mapping) or "pattern" not in d:
        raise ManifestError(f"{where}: a frame must be a mapping with a 'pattern' key, got {d!r}")
    kind = d["pattern"]
    if not isinstance(kind, str) or not kind:  # a number or null would be kept as an unknown kind and ignored
        raise ManifestError(f"{where}: pattern = {kind!r}: must be a name (gray, phase, white, black, or the name "
                            "another program gives its pattern)")
    try:
        if kind == "gray":
            _check_keys(d, _GRAY_KEYS, where)
            return GrayFrame(
                axis=_axis(d, where),
                bit=_whole(_need(d, "bit", where), "bit", where, 0, 30),
                inverted=_flag(d.get("inverted", False), "inverted", where),
                stripe=_whole(d.get("stripe", 1), "stripe", where, 1, 1 << 20),
                xor_with=None if d.get("xor_with") is None else _whole(d["xor_with"], "xor_with", where, 0, 30),
            )
        if kind == "phase":
            _check_keys(d, _PHASE_KEYS, where)
            steps = _whole(_need(d, "steps", where), "steps", where, 3, MAX_PHASE_STEPS)
            return PhaseFrame(
                axis=_axis(d, where),
                period=_finite(_need(d, "period", where), "period", where, 1e6),
                step=_whole(_need(d, "step", where), "step", where, 0, steps - 1),
                steps=steps,
                offset=_finite(d.get("offset", 0.0), "offset", where, 1e6),
            )
    except PatternError as exc:
        raise ManifestError(f"{where}: {exc}") from exc
    except (TypeError, ValueError) as exc:
        raise ManifestError(f"{where}: {exc}; check the frame's keys") from exc
    if kind == "white":
        _check_keys(d, _ANY_KEYS, where)
        return WhiteFrame()
    if kind == "black":
        _check_keys(d, _ANY_KEYS, where)
        return BlackFrame()
    params = tuple((str(k), str(v)) for k, v in d.items() if k not in _ANY_KEYS)
    return OtherFrame(str(kind), params)


def frame_exposure(d: Mapping[str, Any], where: str) -> tuple[float, float] | None:
    """A frame's ``(exposure_us, intensity)``, or None when it states neither.

    Raises
    ------
    ManifestError
        ``exposure_us`` not a finite number > 0, or ``intensity`` not a number in (0, 1].
    """
    if "exposure_us" not in d and "intensity" not in d:
        return None
    exp, inten = d.get("exposure_us", 0.0), d.get("intensity", 1.0)
    for key, val in (("exposure_us", exp), ("intensity", inten)):
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val):
            raise ManifestError(f"{where}: {key} = {val!r}: must be a finite number")
    if "exposure_us" in d and not exp > 0:
        raise ManifestError(f"{where}: exposure_us = {exp!r}: must be > 0 (microseconds)")
    if not 0 < inten <= 1:
        raise ManifestError(f"{where}: intensity = {inten!r}: must be in (0, 1] of the projector's full scale")
    return float(exp), float(inten)


MAX_PHASE_STEPS = 256
"""Most phase steps of one period a manifest may state."""


def _whole(value: Any, key: str, where: str, lo: int, hi: int) -> int:
    """A YAML integer in lo..hi (not a boolean, not a fraction, not a string)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ManifestError(f"{where}: {key} = {value!r}: must be a whole number from {lo} to {hi}")
    if not lo <= value <= hi:
        raise ManifestError(f"{where}: {key} = {value}: must be from {lo} to {hi}")
    return int(value)


def _finite(value: Any, key: str, where: str, limit: float) -> float:
    """A YAML number of magnitude at most ``limit`` (not NaN, not infinite, not a boolean)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ManifestError(f"{where}: {key} = {value!r}: must be a finite number")
    if abs(value) > limit:
        raise ManifestError(f"{where}: {key} = {value!r}: must be within +-{limit:g}")
    return float(value)


def _flag(value: Any, key: str, where: str) -> bool:
    if not isinstance(value, bool):
        raise ManifestError(f"{where}: {key} = {value!r}: must be true or false")
    return value


def _need(d: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in d:
        raise ManifestError(f"{where}: pattern {d['pattern']!r} needs the key {key!r}")
    return d[key]


def _axis(d: Mapping[str, Any], where: str) -> Any:
    axis = _need(d, "axis", where)
    if axis not in ("x", "y"):
        raise ManifestError(f"{where}: axis = {axis!r}: must be 'x' or 'y'")
    return axis


def _check_keys(d: Mapping[str, Any], allowed: set[str], where: str) -> None:
    extra = set(d) - allowed
    if extra:
        raise ManifestError(
            f"{where}: unknown key(s) {sorted(extra)} for pattern {d['pattern']!r}; allowed: {sorted(allowed)}"
        )


def read_manifest(path: str | Path) -> Manifest:
    """Read a manifest file.

    Raises
    ------
    ManifestError
        When the file is missing, not YAML, or inconsistent (names the key and the fix).
    """
    path = Path(path)
    text = read_text_file(path, what="manifest", error=ManifestError, limit_bytes=MAX_MANIFEST_BYTES)
    try:
        doc, _ = parse_yaml(text)
    except DuplicateKeyError as exc:
        where, problem = yaml_problem(exc, str(path))
        raise ManifestError(f"{where}: {problem}") from exc
    except yaml.YAMLError as exc:
        where, problem = yaml_problem(exc, str(path))
        raise ManifestError(f"{where}: not valid YAML: {problem}; check indentation and quoting") from exc
    except RecursionError as exc:
        raise ManifestError(f"{path}: not valid YAML: nested too deeply; a manifest is a few levels deep") from exc
    if not isinstance(doc, dict):
        raise ManifestError(f"{path}: must be a YAML mapping with projector, cameras and frames")
    unknown = set(doc) - {"projector", "cameras", "frames", "stacks", "bit_depth"}
    if unknown:
        raise ManifestError(
            f"{path}: unknown top-level key(s) {sorted(unknown)}; allowed: projector, cameras, frames, stacks, "
            "bit_depth"
        )
    bit_depth = doc.get("bit_depth")
    if bit_depth is not None and (
        isinstance(bit_depth, bool) or not isinstance(bit_depth, int) or not 8 <= bit_depth <= 16
    ):
        raise ManifestError(f"{path}: bit_depth = {bit_depth!r}: must be an integer from 8 to 16 (bits)")
    root = path.parent
    proj = doc.get("projector")
    if not isinstance(proj, dict) or "width" not in proj or "height" not in proj:
        raise ManifestError(f"{path}: projector: must be {{width: W, height: H}} in projector pixels")
    proj_w = _whole(proj["width"], "projector.width", str(path), 1, 100_000)
    proj_h = _whole(proj["height"], "projector.height", str(path), 1, 100_000)
    cameras = doc.get("cameras")
    if not isinstance(cameras, list) or not cameras or not all(isinstance(c, str) for c in cameras):
        raise ManifestError(f"{path}: cameras: must be a non-empty list of camera names")
    frames_doc = doc.get("frames")
    if not isinstance(frames_doc, list) or not frames_doc:
        raise ManifestError(f"{path}: frames: must be a non-empty list")
    stacks_doc = doc.get("stacks")
    frames: list[Frame] = []
    exposures: list[tuple[float, float] | None] = []
    images: dict[str, list[Path]] = {c: [] for c in cameras}
    for i, fd in enumerate(frames_doc):
        where = f"{path}: frames[{i}]"
        frames.append(frame_from_dict(fd, where))
        exposures.append(frame_exposure(fd, where))
        if stacks_doc is not None and "images" in fd:  # which of the two holds the frames?
            raise ManifestError(f"{where}: has images and the manifest has a top-level 'stacks' too; give the "
                                "frames one way, images per frame or one .npy stack per camera")
        if stacks_doc is None:
            imgs = fd.get("images")
            if not isinstance(imgs, dict):
                raise ManifestError(f"{where}: needs images: {{camera: path}} (or a top-level 'stacks')")
            for c in cameras:
                if c not in imgs:
                    raise ManifestError(f"{where}: images: no image for camera {c!r}")
                images[c].append(root / str(imgs[c]))
            extra = sorted(str(c) for c in imgs if c not in cameras)
            if extra:  # a camera left out of cameras: by mistake would be dropped without a word
                raise ManifestError(f"{where}: images: camera(s) {extra} are not in cameras: {list(cameras)}; "
                                    "add them to cameras: to decode them, or remove their images")
    try:
        seq = Sequence(proj_w, proj_h, tuple(frames))
    except PatternError as exc:
        raise ManifestError(f"{path}: {exc}") from exc
    exp = _exposures(exposures, path)
    if stacks_doc is not None:
        if not isinstance(stacks_doc, dict) or set(stacks_doc) != set(cameras):
            raise ManifestError(f"{path}: stacks: must map every camera {cameras} to a .npy file")
        return Manifest(path, seq, tuple(cameras), stacks={c: root / str(stacks_doc[c]) for c in cameras},
                        bit_depth=bit_depth, exposures=exp)
    return Manifest(path, seq, tuple(cameras), images={c: tuple(v) for c, v in images.items()},
                    bit_depth=bit_depth, exposures=exp)


def _exposures(per_frame: list[tuple[float, float] | None], path: Path) -> tuple[tuple[float, float], ...] | None:
    """Every frame's (exposure_us, intensity), or None when no frame states one; all or none must."""
    if all(e is None for e in per_frame):
        return None
    missing = [i for i, e in enumerate(per_frame) if e is None]
    if missing:
        raise ManifestError(
            f"{path}: frames {missing[:8]}{' ...' if len(missing) > 8 else ''} state no exposure_us / intensity "
            "while others do: give every frame of a multi-exposure capture its exposure_us (and intensity)"
        )
    exps = {e[0] for e in per_frame if e is not None}
    if 0.0 in exps and len(exps) > 1:
        raise ManifestError(f"{path}: some frames state exposure_us and some only intensity: state both or one")
    return tuple(e for e in per_frame if e is not None)


def manifest_text(
    sequence: Sequence,
    cameras: list[str] | tuple[str, ...],
    *,
    images: Mapping[str, list[str] | tuple[str, ...]] | None = None,
    stacks: Mapping[str, str] | None = None,
    bit_depth: int | None = None,
    exposures: Sequence_[tuple[float, float]] | None = None,
    source: str = "<manifest>",
) -> str:
    """The YAML text of a manifest (what :func:`write_manifest` writes; the arguments are the same)."""
    if (images is None) == (stacks is None):
        raise ManifestError(f"{source}: give exactly one of images= or stacks=")
    frames: list[dict[str, Any]] = []
    for i, f in enumerate(sequence.frames):
        d = frame_to_dict(f)
        if exposures is not None:
            d["exposure_us"], d["intensity"] = float(exposures[i][0]), float(exposures[i][1])
        if images is not None:
            d["images"] = {c: str(images[c][i]) for c in cameras}
        frames.append(d)
    doc: dict[str, Any] = {
        "projector": {"width": sequence.width, "height": sequence.height},
        "cameras": list(cameras),
    }
    if bit_depth is not None:
        doc["bit_depth"] = int(bit_depth)
    if stacks is not None:
        doc["stacks"] = {c: str(stacks[c]) for c in cameras}
    doc["frames"] = frames
    return str(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120))


def write_manifest(
    path: str | Path,
    sequence: Sequence,
    cameras: list[str] | tuple[str, ...],
    *,
    images: Mapping[str, list[str] | tuple[str, ...]] | None = None,
    stacks: Mapping[str, str] | None = None,
    bit_depth: int | None = None,
    exposures: Sequence_[tuple[float, float]] | None = None,
) -> Path:
    """Write a manifest; ``images``/``stacks`` hold paths relative to the manifest's folder.

    ``bit_depth`` (8..16), when given, is written as the top-level ``bit_depth`` (significant bits);
    ``exposures``, when given, as each frame's ``exposure_us`` and ``intensity``. The file is written
    atomically: a failure (``OutputError``: a full disk, a read-only folder) leaves an old manifest whole.
    """
    path = Path(path)
    text = manifest_text(sequence, cameras, images=images, stacks=stacks, bit_depth=bit_depth,
                         exposures=exposures, source=str(path))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (OSError, ValueError) as exc:  # ValueError: a NUL in the path
        raise ManifestError(f"{str(path)!r}: its folder cannot be made ({getattr(exc, 'strerror', None) or exc}); "
                            "fix the path") from exc
    return write_bytes_atomic(path, text.encode())  # a failure keeps the old manifest whole
