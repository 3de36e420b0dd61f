"""image_transport's compressed formats as the ROS 2 backend reads them (issue 34, item 3): jpeg and
png colour (``compressed``), and 16-bit depth as ``compressedDepth`` (a 12-byte ConfigHeader, then a
16-bit PNG), through CDR as they travel. Bad payloads get a typed error, not a crash."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from libs.ros2 import messages as m


def _roundtrip(msg):
    return m.decode(m.MESSAGES["compressed_image"], m.encode(m.MESSAGES["compressed_image"], msg))


def _scene_rgb() -> np.ndarray:
    y, x = np.mgrid[0:48, 0:64]
    return np.stack([x * 4, y * 5, (x + y) * 2], -1).astype(np.uint8)


def test_png_colour_is_lossless_and_says_its_format():
    rgb = _scene_rgb()
    msg = _roundtrip(m.compressed_image(1.0, "cam", rgb, fmt="png"))
    assert msg.format == "rgb8; png compressed bgr8"
    assert np.array_equal(m.compressed_rgb(msg), rgb)


def test_jpeg_colour_is_close_and_smaller_than_raw():
    rgb = _scene_rgb()
    msg = _roundtrip(m.compressed_image(1.0, "cam", rgb, fmt="jpeg"))
    assert msg.format == "rgb8; jpeg compressed bgr8"
    assert np.abs(m.compressed_rgb(msg).astype(int) - rgb).mean() < 4.0
    assert len(msg.data) < rgb.nbytes


def test_compressed_depth_16uc1_roundtrips_in_millimetres_with_the_plugins_header():
    mm = (np.arange(48 * 64, dtype=np.uint32).reshape(48, 64) * 7 % 9000).astype(np.uint16)
    mm[0, :5] = 0  # no return
    msg = _roundtrip(m.compressed_depth(2.0, "depth", mm))
    assert msg.format == "16UC1; compressedDepth png"
    data = bytes(np.asarray(msg.data, np.uint8))
    fmt, qa, qb = struct.unpack("<iff", data[:12])
    assert (fmt, qa, qb) == (0, 0.0, 0.0)  # INV_DEPTH, parameters unused for 16UC1
    assert data[12:20] == b"\x89PNG\r\n\x1a\n"  # the PNG starts right after the 12-byte header
    d = m.compressed_depth_m(msg)
    assert d.dtype == np.float32 and np.array_equal(np.round(d * 1000).astype(np.uint16), mm)


def test_compressed_depth_32fc1_inverse_depth_is_dequantised():
    import cv2

    depth = np.array([[0.0, 1.0, 2.5], [4.0, 0.5, 10.0]], np.float32)
    # The plugin's quantisation for depth_quantization 100, depth_max 10 m: A = 100 * 101, B = 1 - A / 10.
    a, b = 100.0 * 101.0, 1.0 - 100.0 * 101.0 / 10.0
    with np.errstate(divide="ignore"):
        q = np.where(depth > 0, np.round(a / depth + b), 0).astype(np.uint16)
    ok, png = cv2.imencode(".png", q)
    data = np.frombuffer(struct.pack("<iff", 0, a, b) + png.tobytes(), np.uint8)
    msg = m.new(m.MESSAGES["compressed_image"], header=m.header(0.0, "d"), format="32FC1; compressedDepth png",
                data=data)
    got = m.compressed_depth_m(_roundtrip(msg))
    assert got[0, 0] == 0.0
    np.testing.assert_allclose(got[depth > 0], a / (q[depth > 0] - b), rtol=1e-6)
    np.testing.assert_allclose(got[depth > 0], depth[depth > 0], rtol=0.01)


@pytest.mark.parametrize("fmt,data", [
    ("16UC1; compressedDepth png", b"\x00" * 12),  # a header and nothing after it
    ("16UC1; compressedDepth png", b"\x00" * 12 + b"not a png"),
    ("rgb8; jpeg compressed bgr8", b"\x00" * 40),  # not compressedDepth at all
    ("16UC1; compressedDepth rvl", b"\x00" * 40),
])
def test_bad_compressed_depth_is_a_typed_error(fmt, data):
    msg = m.new(m.MESSAGES["compressed_image"], header=m.header(0.0, "d"), format=fmt,
                data=np.frombuffer(data, np.uint8))
    with pytest.raises(m.CdrError):
        m.compressed_depth_m(msg)


def test_an_8bit_png_is_not_taken_for_depth():
    import cv2

    ok, png = cv2.imencode(".png", np.zeros((4, 4), np.uint8))
    msg = m.new(m.MESSAGES["compressed_image"], header=m.header(0.0, "d"), format="16UC1; compressedDepth png",
                data=np.frombuffer(b"\x00" * 12 + png.tobytes(), np.uint8))
    with pytest.raises(m.CdrError):
        m.compressed_depth_m(msg)
