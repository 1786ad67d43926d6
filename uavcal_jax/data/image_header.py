"""Image size from the file header, without decoding the pixels.

:func:`image_size` reads ``(width, height)`` in pixels of the stored raster from the header of
a PNG (``IHDR``), JPEG (the first start-of-frame marker, baseline or progressive), BMP (the
DIB header) or WebP (``VP8``/``VP8L``/``VP8X`` chunk) file. These are the sizes
``cv2.imread(path, cv2.IMREAD_IGNORE_ORIENTATION)`` returns (EXIF orientation is not applied).
Other formats (TIFF, ...) are decoded once with ``cv2.imread``, the only reader that knows
them all.

A header only proves that the header is sound: a file cut off inside its pixel data still has
a size. Decode the image when that matters.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO

import cv2

from uavcal_jax.errors import DataError

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: JPEG markers that carry no length field (TEM, RST0-7, SOI).
_JPEG_STANDALONE = {0x01, *range(0xD0, 0xD8), 0xD8}
#: Start-of-frame markers SOF0-SOF15 (0xC4 DHT, 0xC8 JPG and 0xCC DAC are not frames).
_JPEG_SOF = set(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def image_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of an image file in pixels, read from its header.

    Raises:
        DataError: naming the file, when it is missing, its header is truncated or corrupt, or
            it is in no format the header reader or OpenCV knows.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(32)
            if head.startswith(_PNG_SIGNATURE):
                size = _png(head)
            elif head.startswith(b"\xff\xd8"):
                size = _jpeg(f)
            elif head.startswith(b"BM"):
                size = _bmp(head)
            elif head[:4] == b"RIFF" and head[8:12] == b"WEBP":
                size = _webp(head)
            else:
                size = None
    except FileNotFoundError:
        raise DataError("missing image", path) from None
    except OSError as err:
        raise DataError(f"cannot read image ({err})", path) from err
    except (ValueError, IndexError, struct.error) as err:
        raise DataError(f"corrupt image header ({err})", path) from err
    if size is None:
        size = _decoded_size(path)
    width, height = size
    if width <= 0 or height <= 0:
        raise DataError(f"corrupt image header (size {width}x{height})", path)
    return width, height


def _png(head: bytes) -> tuple[int, int]:
    if len(head) < 24 or head[12:16] != b"IHDR":
        raise ValueError("no IHDR chunk after the PNG signature")
    width, height = struct.unpack(">II", head[16:24])
    return int(width), int(height)


def _jpeg(f: BinaryIO) -> tuple[int, int]:
    """Walk the marker segments after SOI up to the first start-of-frame."""
    f.seek(2)
    while True:
        byte = f.read(1)
        if not byte:
            raise ValueError("no start-of-frame marker before the end of the file")
        if byte != b"\xff":
            raise ValueError(f"expected a marker, found byte 0x{byte[0]:02x}")
        marker = 0xFF
        while marker == 0xFF:  # any number of 0xFF fill bytes may precede a marker
            byte = f.read(1)
            if not byte:
                raise ValueError("file ends inside a marker")
            marker = byte[0]
        if marker in _JPEG_STANDALONE:
            continue
        if marker in (0xD9, 0xDA):  # EOI, or SOS: entropy-coded data before any frame header
            raise ValueError("no start-of-frame marker before the scan data")
        (length,) = struct.unpack(">H", f.read(2))
        if length < 2:
            raise ValueError(f"segment length {length} < 2")
        if marker in _JPEG_SOF:
            # precision (1 byte), then height and width (2 bytes each)
            _, height, width = struct.unpack(">BHH", f.read(5))
            if height == 0:
                raise ValueError("height 0 (defined later by a DNL marker) is not supported")
            return int(width), int(height)
        f.seek(length - 2, 1)


def _bmp(head: bytes) -> tuple[int, int]:
    (dib_size,) = struct.unpack("<I", head[14:18])
    if dib_size == 12:  # BITMAPCOREHEADER: 16-bit unsigned sizes
        width, height = struct.unpack("<HH", head[18:22])
    elif dib_size >= 40:  # BITMAPINFOHEADER and later: 32-bit signed, height < 0 is top-down
        width, height = struct.unpack("<ii", head[18:26])
    else:
        raise ValueError(f"unknown DIB header size {dib_size}")
    return int(width), abs(int(height))


def _webp(head: bytes) -> tuple[int, int]:
    chunk = head[12:16]
    if chunk == b"VP8 ":  # lossy: 14-bit sizes after the frame tag and start code
        if head[23:26] != b"\x9d\x01\x2a":
            raise ValueError("no VP8 start code")
        width, height = struct.unpack("<HH", head[26:30])
        return width & 0x3FFF, height & 0x3FFF
    if chunk == b"VP8L":  # lossless: signature 0x2f, then 14-bit width-1 and height-1
        if head[20] != 0x2F:
            raise ValueError("no VP8L signature")
        (bits,) = struct.unpack("<I", head[21:25])
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if chunk == b"VP8X":  # extended: 24-bit canvas width-1 and height-1
        return (int.from_bytes(head[24:27], "little") + 1,
                int.from_bytes(head[27:30], "little") + 1)
    raise ValueError(f"unknown WebP chunk {chunk!r}")


def _decoded_size(path: Path) -> tuple[int, int]:
    """A format without a header reader here: decode it once with OpenCV."""
    try:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    except cv2.error:
        image = None
    if image is None or image.size == 0:
        raise DataError("unknown image format or corrupt image", path)
    return int(image.shape[1]), int(image.shape[0])
