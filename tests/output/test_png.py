"""The PNG encoder: read back exactly by an independent decoder (OpenCV), chunks well formed with right CRCs,
bad input refused; and the scan files are written without loading OpenCV."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from appliance.output.png import SIGNATURE, ZLIB_LEVEL, encode_png

ROOT = Path(__file__).resolve().parents[2]


def _image(shape: tuple[int, ...], content: str) -> npt.NDArray[np.uint8]:
    if content == "random":
        return np.random.default_rng(sum(shape)).integers(0, 256, shape, dtype=np.uint8)
    # smooth: gradients and a ring, wrapping through 255 -> 0 (the filter's modulo arithmetic)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    base = 0.4 * xx + 0.7 * yy + 40 * np.sin(np.hypot(xx - shape[1] / 3, yy - shape[0] / 2) / 9)
    if len(shape) == 3:
        base = base[:, :, None] + np.array([0.0, 85.0, 170.0])
    img: npt.NDArray[np.uint8] = (np.floor(base) % 256).astype(np.uint8)
    return img


def _decode_cv2(data: bytes) -> npt.NDArray[Any]:
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None, "OpenCV could not decode the PNG"
    return np.asarray(img)


def _chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """(type, data) of every chunk, after checking the signature, each length and each CRC."""
    assert data[:8] == SIGNATURE
    out, pos = [], 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        assert len(body) == length, f"chunk {kind!r} runs past the end of the file"
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + body), f"chunk {kind!r} at byte {pos}: bad CRC"
        out.append((kind, body))
        pos += 12 + length
    assert pos == len(data)
    return out


SHAPES = [(1, 1), (3, 7), (1023, 1281)]


@pytest.mark.parametrize("content", ["random", "smooth"])
@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("hw", SHAPES, ids=[f"{h}x{w}" for h, w in SHAPES])
def test_read_back_exactly_by_opencv(hw: tuple[int, int], channels: int, content: str) -> None:
    img = _image(hw if channels == 1 else (*hw, 3), content)
    back = _decode_cv2(encode_png(img))
    assert back.dtype == np.uint8 and back.shape == img.shape
    np.testing.assert_array_equal(back, img)  # (OpenCV decodes to BGR: the channel order went through right)


@pytest.mark.parametrize("channels", [1, 3])
def test_chunks_and_stream(channels: int) -> None:
    """Signature, IHDR first and IEND last, every CRC right; the IDAT data is one zlib stream of rows, each a
    'Sub' filter byte and the row's differences, which undo (here, independently) to the image in RGB order."""
    h, w = 37, 53
    img = _image((h, w) if channels == 1 else (h, w, 3), "smooth")
    chunks = _chunks(encode_png(img))
    kinds = [k for k, _ in chunks]
    assert kinds[0] == b"IHDR" and kinds[-1] == b"IEND" and chunks[-1][1] == b""
    assert set(kinds[1:-1]) == {b"IDAT"}
    width, height, depth, colour, comp, filt, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert (width, height, depth, comp, filt, interlace) == (w, h, 8, 0, 0, 0)
    assert colour == (0 if channels == 1 else 2)
    raw = np.frombuffer(zlib.decompress(b"".join(b for k, b in chunks if k == b"IDAT")), np.uint8)
    rows = raw.reshape(h, 1 + w * channels)
    assert np.all(rows[:, 0] == 1)  # 'Sub'
    diffs = rows[:, 1:].reshape(h, w, channels).astype(np.int64)
    unfiltered = (np.cumsum(diffs, axis=1) % 256).astype(np.uint8)
    expected = img[:, :, None] if channels == 1 else img[:, :, ::-1]
    np.testing.assert_array_equal(unfiltered, expected)


def test_strided_views_encode_like_copies() -> None:
    img = _image((40, 60, 3), "random")
    for view in (img[::2, ::3], img[:, ::-1], img[5:30, 7:50], img[:, :, 1], np.asfortranarray(img)):
        np.testing.assert_array_equal(_decode_cv2(encode_png(view)), view)
        assert encode_png(view) == encode_png(np.ascontiguousarray(view))


def test_filter_helps_on_smooth_content() -> None:
    """A smooth colour picture compresses to well below its raw size, and clearly better than deflating its
    unfiltered bytes at the same level would."""
    img = _image((512, 640, 3), "smooth")
    size = len(encode_png(img))
    assert size < img.nbytes / 5
    assert size < 0.8 * len(zlib.compress(img.tobytes(), ZLIB_LEVEL))


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (np.zeros((4, 4), np.float32), r"image dtype = float32: must be uint8"),
        (np.zeros((4, 4), np.uint16), r"image dtype = uint16: must be uint8"),
        (np.zeros((4, 4, 4), np.uint8), r"image shape = \(4, 4, 4\): must be \(H, W\) or \(H, W, 3\)"),
        (np.zeros((4, 4, 1), np.uint8), r"image shape = \(4, 4, 1\)"),
        (np.zeros((4,), np.uint8), r"image shape = \(4,\)"),
        (np.zeros((0, 5, 3), np.uint8), r"image shape = \(0, 5, 3\): .* H, W >= 1"),
        ([[1, 2], [3, 4]], r"image = list: must be a numpy array"),
    ],
)
def test_bad_images_refused(image: Any, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        encode_png(image)


def test_scan_files_without_opencv() -> None:
    """The service's output path (cloud, preview, sidecar) in a fresh interpreter never imports cv2."""
    code = """
import sys
import numpy as np
from appliance.output.scanfiles import scan_file_contents
from appliance.output.sidecar import ScanMetadata
from appliance.reconstruct.types import PointCloud

rng = np.random.default_rng(1)
n = 4000
cloud = PointCloud(
    xyz=(rng.normal(size=(n, 3)) * 20 + [0, 0, 600]).astype(np.float32),
    row=rng.integers(0, 96, n).astype(np.int32), col=rng.integers(0, 128, n).astype(np.int32),
    camera=rng.integers(0, 2, n).astype(np.uint8), intensity=rng.integers(0, 256, n).astype(np.uint8),
    quality=rng.random(n).astype(np.float32), normal=None,
)
meta = ScanMetadata("20261202-014512-SIM0001-000012", "2026-12-02T01:45:12+00:00", {}, "abc", {"points": n}, {},
                    "SIM0001")
files = scan_file_contents(meta, cloud, [(96, 128), (96, 128)], preview=True)
png = [f for f in files if f.name.endswith(".png")]
assert len(png) == 1 and b"".join(bytes(c) for c in png[0].chunks())[:8] == b"\\x89PNG\\r\\n\\x1a\\n"
print("cv2 loaded:", "cv2" in sys.modules)
"""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT,
                         env=env, check=False)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "cv2 loaded: False"
