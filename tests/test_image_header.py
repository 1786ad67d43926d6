"""The image-header reader against OpenCV's decoded sizes, and its errors on bad files."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from uavcal_jax.data.image_header import image_size
from uavcal_jax.errors import DataError

SIZES = [(37, 23), (1, 1), (640, 480), (300, 1200)]  # (width, height)


def _write(path, w, h, channels=3, params=()):
    rng = np.random.default_rng(w * 7919 + h)
    shape = (h, w) if channels == 1 else (h, w, channels)
    assert cv2.imwrite(str(path), rng.integers(0, 256, shape, dtype=np.uint8), list(params))
    return path


CASES = [
    ("png", 3, ()), ("png", 1, ()), ("png", 4, ()),
    ("jpg", 3, ()), ("jpg", 1, ()),
    ("jpg", 3, (cv2.IMWRITE_JPEG_PROGRESSIVE, 1)),
    ("bmp", 3, ()), ("bmp", 1, ()),
    ("webp", 3, (cv2.IMWRITE_WEBP_QUALITY, 101)),  # lossless: VP8L
    ("webp", 3, (cv2.IMWRITE_WEBP_QUALITY, 80)),  # lossy: VP8
    ("tiff", 3, ()),  # no header reader: decoded by OpenCV
]


@pytest.mark.parametrize("ext,channels,params", CASES)
@pytest.mark.parametrize("w,h", SIZES)
def test_size_equals_opencv_decode(tmp_path, ext, channels, params, w, h):
    path = _write(tmp_path / f"img.{ext}", w, h, channels, params)
    decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    assert image_size(path) == (decoded.shape[1], decoded.shape[0]) == (w, h)


def test_jpeg_with_exif_like_app_segments(tmp_path):
    """Segments before the frame header (APP1, COM) are skipped by their lengths."""
    path = _write(tmp_path / "a.jpg", 50, 20)
    data = path.read_bytes()
    app1 = b"\xff\xe1" + (2 + 300).to_bytes(2, "big") + b"Exif\x00\x00" + bytes(294)
    com = b"\xff\xfe" + (2 + 5).to_bytes(2, "big") + b"hello"
    path.write_bytes(data[:2] + app1 + com + b"\xff\xff" + data[2:])  # and a fill byte
    assert cv2.imread(str(path)).shape[:2] == (20, 50)
    assert image_size(path) == (50, 20)


@pytest.mark.parametrize("ext", ["png", "jpg", "bmp", "webp"])
def test_truncated_header_is_a_data_error_naming_the_file(tmp_path, ext):
    path = _write(tmp_path / f"cut.{ext}", 64, 48)
    data = path.read_bytes()
    keep = {"png": 20, "jpg": 4, "bmp": 20, "webp": 22}[ext]
    path.write_bytes(data[:keep])
    assert cv2.imread(str(path)) is None
    with pytest.raises(DataError, match="cut") as err:
        image_size(path)
    assert err.value.path == path


def test_corrupt_unknown_and_missing_files(tmp_path):
    png = _write(tmp_path / "bad.png", 8, 8)
    data = bytearray(png.read_bytes())
    data[12:16] = b"XXXX"  # the IHDR chunk type
    png.write_bytes(bytes(data))
    with pytest.raises(DataError, match="corrupt image header"):
        image_size(png)
    jpg = _write(tmp_path / "bad.jpg", 8, 8)
    jpg.write_bytes(jpg.read_bytes()[:2] + b"\x00garbage")
    with pytest.raises(DataError, match="expected a marker"):
        image_size(jpg)
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"not an image at all")
    with pytest.raises(DataError, match="unknown image format"):
        image_size(garbage)
    empty = tmp_path / "empty.jpg"
    empty.write_bytes(b"")
    with pytest.raises(DataError, match="empty.jpg"):
        image_size(empty)
    with pytest.raises(DataError, match="missing image"):
        image_size(tmp_path / "nope.png")
