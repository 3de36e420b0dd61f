"""Key expressions, attachments and liveliness tokens against ros2/rmw_zenoh docs/design.md's
examples, verbatim; and the zenoh-bridge-ros2dds style."""

from __future__ import annotations

import struct

import pytest

from libs.ros2.keys import (
    ATTACHMENT_SIZE, Attachment, BridgeKeys, EntityKind, Qos, RmwZenohKeys, RosNameError, key_style, mangle,
)
from libs.ros2.messages import RosType
from libs.ros2.profiles import PROFILES, Ros2Profile, UnknownProfileError, profile

STRING = RosType("std_msgs/msg/String")
HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"


class _AddTwoInts(RosType):
    # The design doc's service example; the hash is checked separately (test_ros2_messages).
    @property
    def type_hash(self) -> str:
        return ADD_HASH


ADD = _AddTwoInts("example_interfaces/srv/AddTwoInts")


def test_topic_keys_of_the_design_document():
    assert RmwZenohKeys().topic_key("chatter", STRING) == f"0/chatter/std_msgs::msg::dds_::String_/{HASH}"
    assert RmwZenohKeys(namespace="/robot1").topic_key("chatter", STRING) == f"0/robot1/chatter/std_msgs::msg::dds_::String_/{HASH}"
    assert RmwZenohKeys(domain_id=2).service_key("add_two_ints", ADD) == \
        f"2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_HASH}"
    # An absolute name ignores the namespace (ROS 2 name resolution).
    assert RmwZenohKeys(namespace="/robot1").topic_key("/chatter", STRING).startswith("0/chatter/")


def test_liveliness_tokens_of_the_design_document():
    k = RmwZenohKeys(domain_id=2)
    assert k.node_token("aac3178e146ba6f1fc6e6a4085e77f21", 0, "listener") == \
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert k.entity_token("aac3178e146ba6f1fc6e6a4085e77f21", 0, 10, EntityKind.SUBSCRIPTION, "listener", "chatter",
                          STRING, Qos(depth=10)) == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        f"{HASH}/::,10:,:,:,,")
    assert k.entity_token("8b20917502ee955ac4476e0266340d5c", 0, 10, EntityKind.PUBLISHER, "talker", "chatter",
                          STRING, Qos(depth=7)) == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{HASH}/::,7:,:,:,,")
    assert k.entity_token("f9980ee0495eaafb3e38f0d19e2eae12", 0, 10, EntityKind.SERVICE, "add_two_ints_server",
                          "add_two_ints", ADD, Qos()) == (
        "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/%add_two_ints/"
        f"example_interfaces::srv::dds_::AddTwoInts_/{ADD_HASH}/::,10:,:,:,,")
    assert k.entity_token("e1dc8d1b45ae8717fce78689cc655685", 0, 10, EntityKind.CLIENT, "add_two_ints_client",
                          "add_two_ints", ADD, Qos()) == (
        "@ros2_lv/2/e1dc8d1b45ae8717fce78689cc655685/0/10/SC/%/%/add_two_ints_client/%add_two_ints/"
        f"example_interfaces::srv::dds_::AddTwoInts_/{ADD_HASH}/::,10:,:,:,,")


def test_namespaced_tokens_mangle_every_slash():
    k = RmwZenohKeys(namespace="/robot1/arm")
    tok = k.entity_token("z", 0, 3, EntityKind.PUBLISHER, "n", "odom", STRING, Qos())
    assert "/%robot1%arm/n/%robot1%arm%odom/" in tok
    assert mangle("") == "%"


def test_qos_keyexpr_omits_defaults():
    assert Qos().keyexpr() == "::,10:,:,:,,"
    assert Qos(depth=42).keyexpr() == "::,:,:,:,,"
    assert Qos(reliable=False, transient_local=True, depth=1).keyexpr() == "2:1:,1:,:,:,,"


def test_attachment_is_33_bytes_sequence_timestamp_gid():
    gid = bytes(range(16))
    a = Attachment(7, 1_700_000_000_123_456_789, gid)
    data = a.encode()
    assert len(data) == ATTACHMENT_SIZE == 33
    assert data == struct.pack("<q", 7) + struct.pack("<q", 1_700_000_000_123_456_789) + b"\x10" + gid
    assert Attachment.decode(data) == a
    for bad in (None, data[:20], data[:16] + b"\x08" + gid):
        with pytest.raises(RosNameError):
            Attachment.decode(bad)


def test_bridge_keys_are_the_ros_name_without_its_slash_under_an_optional_prefix():
    assert BridgeKeys().topic_key("/stretch/cmd_vel", STRING) == "stretch/cmd_vel"
    assert BridgeKeys(prefix="robot1").topic_key("/odom", STRING) == "robot1/odom"
    assert BridgeKeys(namespace="/ns").topic_key("scan", STRING) == "ns/scan"
    assert BridgeKeys().node_token("z", 0, "n") is None and not BridgeKeys().attachments


def test_bad_names_domains_and_styles_are_refused():
    for bad in ("", "/a//b", "a b", "1abc", "/odom/"):
        with pytest.raises(RosNameError):
            BridgeKeys().topic_key(bad, STRING)
    with pytest.raises(RosNameError):
        RmwZenohKeys(domain_id=300)
    with pytest.raises(RosNameError):
        key_style("dds")


def test_profiles_are_data_and_overrides_are_validated():
    s = PROFILES["stretch"]
    assert s.cmd_vel == "/stretch/cmd_vel" and s.depth == "/camera/aligned_depth_to_color/image_raw"
    assert s.depth_encoding == "16UC1" and s.nav_mode_service == "/switch_to_navigation_mode"
    assert s.run_stop and s.camera_rotation_quarters == 1 and s.teleport_service is None
    g = profile("generic", {"odom": "/wheel/odom", "depth": None, "color_encoding": "jpeg"})
    assert g.odom == "/wheel/odom" and g.depth is None and g.color_encoding == "jpeg"
    with pytest.raises(UnknownProfileError):
        profile("roomba")
    with pytest.raises(ValueError):
        profile("generic", {"max_linear_mps": -1})
    with pytest.raises(ValueError):
        profile("generic", {"unknown_field": 1})
    assert isinstance(g, Ros2Profile)
