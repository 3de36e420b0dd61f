"""CDR of every ROS 2 message robot-io uses, through the rosbags typestore: round trips, the wire
layout pinned by hand for small messages, type hashes against rmw_zenoh's documented examples."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from libs.ros2 import messages as m

DESIGN_MD_HASHES = {  # ros2/rmw_zenoh docs/design.md, "Topic and Service name mapping"
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "example_interfaces/srv/AddTwoInts": "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a",
}


def roundtrip(name, msg):
    data = m.encode(name, msg)
    assert data[:4] == b"\x00\x01\x00\x00"  # CDR little endian encapsulation
    return m.decode(name, data)


def test_type_hashes_match_the_design_document():
    assert m.type_hash("std_msgs/msg/String") == DESIGN_MD_HASHES["std_msgs/msg/String"]
    # A service's hash covers request, response and event (REP-2016); registered like ours.
    store = m.typestore()
    store.register(m.service_types("example_interfaces/srv/AddTwoInts", "int64 a\nint64 b\n", "int64 sum\n"))
    m._fix_char_arrays(store)
    assert store.hash_rihs01("example_interfaces/srv/AddTwoInts") == DESIGN_MD_HASHES["example_interfaces/srv/AddTwoInts"]


def test_every_message_and_service_used_has_a_type_hash_and_a_dds_name():
    for name in [*m.MESSAGES.values(), *m.SERVICES]:
        h = m.type_hash(name)
        assert h.startswith("RIHS01_") and len(h) == 7 + 64
    assert m.RosType("sensor_msgs/msg/Image").dds_name == "sensor_msgs::msg::dds_::Image_"
    assert m.RosType("std_srvs/srv/Trigger").dds_name == "std_srvs::srv::dds_::Trigger_"


def test_twist_wire_layout_is_six_little_endian_doubles():
    data = m.encode(m.MESSAGES["twist"], m.twist(0.25, -0.5))
    assert data == b"\x00\x01\x00\x00" + struct.pack("<6d", 0.25, 0, 0, 0, 0, -0.5)


def test_bool_and_clock_wire_layout():
    assert m.encode(m.MESSAGES["bool"], m.boolean(True)) == b"\x00\x01\x00\x00\x01"
    assert m.encode(m.MESSAGES["clock"], m.clock(12.5)) == b"\x00\x01\x00\x00" + struct.pack("<iI", 12, 500_000_000)


def test_trigger_request_and_response_wire_layout():
    assert m.encode("std_srvs/srv/Trigger_Request", m.new("std_srvs/srv/Trigger_Request")) == b"\x00\x01\x00\x00\x00"
    data = m.encode("std_srvs/srv/Trigger_Response", m.trigger_response(True, "ok"))
    # bool, pad to 4, uint32 length incl. NUL, bytes + NUL
    assert data == b"\x00\x01\x00\x00" + b"\x01\x00\x00\x00" + struct.pack("<I", 3) + b"ok\x00"


@pytest.mark.parametrize("encoding,array", [
    ("rgb8", np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)),
    ("bgr8", np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)[::-1].copy()),
    ("16UC1", (np.arange(20, dtype=np.uint16) * 997).reshape(4, 5)),
    ("32FC1", np.linspace(0.0, 7.5, 20, dtype=np.float32).reshape(4, 5)),
    ("32SC1", np.arange(-5, 15, dtype=np.int32).reshape(4, 5)),
])
def test_image_round_trips_in_every_encoding(encoding, array):
    back = roundtrip(m.MESSAGES["image"], m.image(3.25, "cam", array, encoding))
    assert back.encoding == encoding and back.header.frame_id == "cam" and m.stamp_s(back.header.stamp) == 3.25
    np.testing.assert_array_equal(m.image_array(back), array)


def test_image_with_row_padding_and_big_endian_data_is_read_correctly():
    a = (np.arange(12, dtype=np.uint16) * 300).reshape(3, 4)
    msg = m.image(0.0, "cam", a, "16UC1")
    rows = np.zeros((3, 10), np.uint8)  # step 10 > 8: two bytes of padding per row
    rows[:, :8] = a.astype(">u2").view(np.uint8).reshape(3, 8)
    msg.data, msg.step, msg.is_bigendian = rows.reshape(-1), 10, 1
    np.testing.assert_array_equal(m.image_array(roundtrip(m.MESSAGES["image"], msg)), a)


def test_image_whose_size_does_not_fit_its_data_is_refused():
    msg = m.image(0.0, "cam", np.zeros((4, 4, 3), np.uint8), "rgb8")
    msg.height = 400
    with pytest.raises(m.CdrError):
        m.image_array(msg)
    msg = m.image(0.0, "cam", np.zeros((4, 4, 3), np.uint8), "rgb8")
    msg.encoding = "yuv422"
    with pytest.raises(m.CdrError):
        m.image_array(msg)


def test_compressed_image_round_trip_keeps_the_picture():
    rgb = np.zeros((32, 48, 3), np.uint8)
    rgb[:, :24] = (200, 30, 30)
    back = roundtrip(m.MESSAGES["compressed_image"], m.compressed_image(1.0, "cam", rgb))
    out = m.compressed_rgb(back)
    assert out.shape == rgb.shape and np.abs(out.astype(int) - rgb.astype(int)).mean() < 6


def test_camera_info_odometry_imu_scan_tf_map_round_trip():
    ci = roundtrip(m.MESSAGES["camera_info"], m.camera_info(1.0, "cam", 640, 480, 600.0, 601.0, 319.5, 239.5))
    assert (ci.width, ci.height) == (640, 480) and list(ci.k) == [600, 0, 319.5, 0, 601, 239.5, 0, 0, 1]
    od = roundtrip(m.MESSAGES["odometry"], m.odometry(2.0, (1.0, -2.0, 0.5), 0.75, 0.2, -0.1))
    assert (od.pose.pose.position.x, od.pose.pose.position.y, od.pose.pose.position.z) == (1.0, -2.0, 0.5)
    assert math.isclose(m.yaw_from_quaternion(od.pose.pose.orientation), 0.75, abs_tol=1e-12)
    assert od.twist.twist.linear.x == 0.2 and od.twist.twist.angular.z == -0.1 and od.child_frame_id == "base_link"
    im = roundtrip(m.MESSAGES["imu"], m.imu(2.0, "imu", -2.5, 0.3))
    assert math.isclose(m.yaw_from_quaternion(im.orientation), -2.5, abs_tol=1e-12)
    r = np.array([1.0, np.inf, 2.5, 0.3], np.float32)
    sc = roundtrip(m.MESSAGES["scan"], m.laser_scan(2.0, "laser", r, -math.pi, math.pi / 2, 0.05, 8.0))
    np.testing.assert_array_equal(sc.ranges, r)
    assert math.isclose(sc.angle_max, -math.pi + 3 * math.pi / 2, abs_tol=1e-6)
    tf = roundtrip(m.MESSAGES["tf"], m.tf_message([m.transform_stamped(2.0, "odom", "base_link", (1, 2, 0), 0.5)]))
    assert tf.transforms[0].child_frame_id == "base_link" and tf.transforms[0].transform.translation.y == 2
    grid = np.array([[0, 100, -1], [0, 0, 100]], np.int8)
    og = roundtrip(m.MESSAGES["occupancy_grid"], m.occupancy_grid(2.0, "map", grid, 0.05, (-1.0, 2.0)))
    assert (og.info.width, og.info.height) == (3, 2) and og.info.resolution == pytest.approx(0.05)
    np.testing.assert_array_equal(np.asarray(og.data).reshape(2, 3), grid)


def test_teleport_service_round_trip():
    req = roundtrip("turtlesim/srv/TeleportAbsolute_Request",
                    m.new("turtlesim/srv/TeleportAbsolute_Request", x=1.5, y=-2.0, theta=0.25))
    assert (req.x, req.y, req.theta) == (1.5, -2.0, 0.25)


def test_a_truncated_or_foreign_payload_is_a_typed_error():
    data = m.encode(m.MESSAGES["odometry"], m.odometry(2.0, (1, 2, 0), 0.1, 0, 0))
    with pytest.raises(m.CdrError):
        m.decode(m.MESSAGES["odometry"], data[:40])
    with pytest.raises(m.CdrError):
        m.decode(m.MESSAGES["image"], b"\x00\x01\x00\x00garbage")
    with pytest.raises(m.CdrError):
        m.type_hash("nope_msgs/msg/Nothing")
