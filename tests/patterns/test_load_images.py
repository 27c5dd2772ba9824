"""A manifest's image frames read on several threads: the same stack as one thread, bad frames named in order.

The speed (an 88-frame batch of 1920x1280 JPEGs) is measured by ``scripts/bench_stereo.py``, not here.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.errors import ManifestError
from appliance.patterns.manifest import load_images


def _frames(folder: Path, n: int, ext: str, dtype: type = np.uint8) -> list[Path]:
    rng = np.random.default_rng(3)
    top = 255 if dtype == np.uint8 else 4095
    paths = []
    for i in range(n):
        img = (rng.random((48, 64)) * top).astype(dtype)
        img[:, (i * 3) % 64] = top  # every frame differs where a mix-up would show
        paths.append(folder / f"{i:02d}.{ext}")
        cv2.imwrite(str(paths[-1]), img)
    return paths


@pytest.mark.parametrize(("ext", "dtype"), [("png", np.uint8), ("png", np.uint16), ("jpg", np.uint8)])
def test_threads_read_the_same_stack_in_capture_order(tmp_path: Path, ext: str, dtype: type) -> None:
    paths = _frames(tmp_path, 17, ext, dtype)
    one = load_images(paths, threads=1)
    many = load_images(paths, threads=4)
    assert one.shape == (17, 48, 64) and one.dtype == dtype
    np.testing.assert_array_equal(many, one)
    for i, p in enumerate(paths):  # frame i is file i
        np.testing.assert_array_equal(many[i], cv2.imread(str(p), cv2.IMREAD_UNCHANGED))


@pytest.mark.parametrize(("ext", "dtype"), [("png", np.uint8), ("png", np.uint16), ("jpg", np.uint8)])
def test_colour_frames_become_grey_at_their_bit_depth(tmp_path: Path, ext: str, dtype: type) -> None:
    paths = _frames(tmp_path, 4, ext, dtype)
    rng = np.random.default_rng(5)
    grey = cv2.imread(str(paths[2]), cv2.IMREAD_UNCHANGED)
    colour = np.dstack([grey, grey, grey]).astype(np.float64)
    colour += rng.normal(0, 0.02 * np.iinfo(dtype).max, colour.shape)  # channels that differ
    colour = np.clip(colour, 0, np.iinfo(dtype).max).astype(dtype)
    cv2.imwrite(str(paths[2]), colour)
    stack = load_images(paths, threads=3)
    assert stack.dtype == dtype
    # the grey of the decoded colour image by the ITU-R 601 weights, within the decoders' rounding: a PNG's
    # grey comes from libpng's fixed-point weights (1 DN), a JPEG's is its luma plane as stored (2 DN)
    expected = cv2.cvtColor(cv2.imread(str(paths[2]), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2GRAY)
    diff = np.abs(stack[2].astype(np.int64) - expected.astype(np.int64))
    assert diff.max() <= (2 if ext == "jpg" else 1), diff.max()


def test_the_first_bad_frame_in_capture_order_is_named(tmp_path: Path) -> None:
    paths = _frames(tmp_path, 12, "png")
    cv2.imwrite(str(paths[9]), np.zeros((10, 10), np.uint8))  # a frame of another size, late
    paths[5].unlink()  # and a missing one before it
    with pytest.raises(ManifestError, match=r"scan\.yaml: frame 5: image .*05\.png is missing or unreadable"):
        load_images(paths, "scan.yaml", threads=4)
    cv2.imwrite(str(paths[5]), cv2.imread(str(paths[4]), cv2.IMREAD_UNCHANGED))
    with pytest.raises(ManifestError, match=r"frame 9: .* is 10x10 uint8, but frame 0 is 64x48 uint8"):
        load_images(paths, "scan.yaml", threads=4)
    with pytest.raises(ManifestError, match="no frames"):
        load_images([], "scan.yaml")


def _jpegs(folder: Path, n: int, size: tuple[int, int], params: list[int], colour: bool) -> list[Path]:
    rng = np.random.default_rng(11)
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w]
    paths = []
    for i in range(n):
        stripes = np.where(((xx + 3 * i) // (1 + i % 4)) % 2 == 0, 200.0, 40.0) * (0.6 + 0.4 * yy / h)
        img = np.clip(stripes + rng.normal(0, 6, (h, w)), 0, 255).astype(np.uint8)
        if colour:  # channels that differ, so a wrong grey would show
            img = np.dstack([img, np.roll(img, 1, axis=1), np.clip(img.astype(int) + 30, 0, 255).astype(np.uint8)])
        paths.append(folder / f"{i:02d}.jpg")
        cv2.imwrite(str(paths[-1]), img, params)
    return paths


@pytest.mark.parametrize(
    ("size", "params", "colour"),
    [((96, 160), [cv2.IMWRITE_JPEG_QUALITY, 90], False),
     ((97, 161), [cv2.IMWRITE_JPEG_QUALITY, 75], True),  # odd size, 4:2:0 chroma
     ((64, 80), [cv2.IMWRITE_JPEG_QUALITY, 95, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                 cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444], True),
     ((64, 80), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1], True)],
)  # fmt: skip
def test_jpegs_decoded_into_the_stack_equal_opencvs_grey(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, size: tuple[int, int], params: list[int], colour: bool
) -> None:
    """libjpeg-turbo's decode straight into the stack gives OpenCV's grey bit for bit, and is the path taken."""
    from appliance.patterns import manifest

    assert manifest._simplejpeg is not None, "simplejpeg is a dependency: the fast path must be there"
    paths = _jpegs(tmp_path, 9, size, params, colour)
    calls = {"n": 0}
    real = manifest._simplejpeg.decode_jpeg

    class Spy:
        decode_jpeg_header = staticmethod(manifest._simplejpeg.decode_jpeg_header)

        @staticmethod
        def decode_jpeg(*a: object, **k: object) -> object:
            calls["n"] += 1
            return real(*a, **k)

    monkeypatch.setattr(manifest, "_simplejpeg", Spy)
    fast = load_images(paths, threads=2)
    assert calls["n"] == len(paths) - 1  # every frame after the first went straight into the stack
    monkeypatch.setattr(manifest, "_simplejpeg", None)  # OpenCV alone, as where simplejpeg is missing
    slow = load_images(paths, threads=2)
    np.testing.assert_array_equal(fast, slow)
    flags = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION
    for i, p in enumerate(paths):
        np.testing.assert_array_equal(fast[i], cv2.imread(str(p), flags))


def test_a_jpeg_the_fast_path_cannot_take_is_decoded_or_named(tmp_path: Path) -> None:
    """A JPEG of another size is named as before; a corrupt one (no clean decode) is left to OpenCV's verdict."""
    paths = _jpegs(tmp_path, 6, (48, 64), [cv2.IMWRITE_JPEG_QUALITY, 90], False)
    cv2.imwrite(str(paths[4]), np.zeros((40, 64), np.uint8))
    with pytest.raises(ManifestError, match=r"frame 4: .* is 64x40 uint8, but frame 0 is 64x48 uint8"):
        load_images(paths, "scan.yaml", threads=2)
    data = bytearray(paths[0].read_bytes())
    data[len(data) // 2 : len(data) // 2 + 40] = b"\xff\x00" * 20  # damaged entropy data, end marker intact
    paths[4].write_bytes(bytes(data))
    stack = load_images(paths, "scan.yaml", threads=2)  # libjpeg recovers what it can, as OpenCV did before
    ref = cv2.imdecode(np.frombuffer(bytes(data), np.uint8), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(stack[4], ref)
