"""Writes foxglove-protobuf.mcap: images as another tool writes them (not run by the tests).

The fixture checks that replay reads Foxglove's protobuf images written by the official tooling,
not only dyknow's own encoder. It was made with a virtual environment holding
``protobuf foxglove-schemas-protobuf mcap-protobuf-support numpy`` (protobuf 7.36.2,
foxglove-schemas-protobuf 0.4.0, mcap-protobuf-support 0.6.0, mcap 1.6.0)::

    python tests/mcap/make_foxglove_protobuf.py tests/mcap/foxglove-protobuf.mcap

Content (tests/recording/test_codecs.py rebuilds the expected arrays with the same formulas):

- ``/camera/rgb``: 3 ``foxglove.RawImage`` ``rgb8`` 4x3 images with rows padded to 16 bytes;
  pixel (x, y) of frame i is (R, G, B) = (10 * i + x, 100 + y, 200); log_time 1000 + i.
- ``/camera/depth``: 1 ``mono16`` 5x2 image, pixel (x, y) = 1000 * y + x; log_time 1010.
- ``/camera/png``: 1 ``foxglove.CompressedImage``, a 4x4 8-bit grey PNG, pixel (x, y) = 16 * y + x;
  log_time 1020.
- ``/same/raw`` and ``/same/png``: a ``bgr8`` 3x2 image (bytes 0..17, timestamp 1030 ns) and the
  PNG above (format png, timestamp 1040 ns), with no frame_id: what dyknow's own encoder writes for
  that array and those bytes, so a test compares the two byte for byte.
"""

from __future__ import annotations

import struct
import sys
import zlib

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap_protobuf.writer import Writer


def png_grey(pixels: np.ndarray) -> bytes:
    height, width = pixels.shape

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    rows = b"".join(b"\x00" + pixels[y].astype(np.uint8).tobytes() for y in range(height))
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")


def main(path: str) -> None:
    with open(path, "wb") as file:
        writer = Writer(file)
        for i in range(3):
            image = np.zeros((3, 16), np.uint8)  # 4 pixels of 3 bytes, then 4 bytes of padding per row
            for y in range(3):
                for x in range(4):
                    image[y, 3 * x : 3 * x + 3] = (10 * i + x, 100 + y, 200)
            msg = RawImage(width=4, height=3, encoding="rgb8", step=16, data=image.tobytes(), frame_id="cam")
            msg.timestamp.FromNanoseconds(1000 + i)
            writer.write_message("/camera/rgb", msg, log_time=1000 + i, publish_time=1000 + i, sequence=i)
        depth = np.array([[1000 * y + x for x in range(5)] for y in range(2)], "<u2")
        msg = RawImage(width=5, height=2, encoding="mono16", step=10, data=depth.tobytes())
        writer.write_message("/camera/depth", msg, log_time=1010, publish_time=1010)
        grey = np.array([[16 * y + x for x in range(4)] for y in range(4)], np.uint8)
        png = CompressedImage(format="png", data=png_grey(grey), frame_id="cam")
        writer.write_message("/camera/png", png, log_time=1020, publish_time=1020)
        same = RawImage(width=3, height=2, encoding="bgr8", step=9, data=bytes(range(18)))
        same.timestamp.FromNanoseconds(1030)
        writer.write_message("/same/raw", same, log_time=1030, publish_time=1030)
        same_png = CompressedImage(format="png", data=png_grey(grey))
        same_png.timestamp.FromNanoseconds(1040)
        writer.write_message("/same/png", same_png, log_time=1040, publish_time=1040)
        writer.finish()


if __name__ == "__main__":
    main(sys.argv[1])
