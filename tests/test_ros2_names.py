"""dyknow.ros2.names against rmw_zenoh's own documentation (``docs/design.md`` of ros2/rmw_zenoh,
the examples of "Topic and Service name mapping to Zenoh key expressions" and "Graph Cache",
copied verbatim), and the GID against XXH3's published test vector."""

from __future__ import annotations

import pytest

from dyknow.errors import BindingError
from dyknow.ros2 import names
from dyknow.ros2.names import Durability, Entity, EntityKind, QoS, Reliability

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"

# design.md, "Topic and Service name mapping to Zenoh key expressions"
DOC_KEYS = [
    ((0, "/chatter", "std_msgs/msg/String", STRING_HASH), f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"),
    ((0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH), f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"),
    (
        (2, "/add_two_ints", "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH),
        f"2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}",
    ),
]

# design.md, "Graph Cache": the demo_nodes_cpp examples
DOC_TOKENS = [
    "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener",
    f"@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,",
    f"@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,",
    "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/%add_two_ints/"
    f"example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}/::,10:,:,:,,",
    "@ros2_lv/2/e1dc8d1b45ae8717fce78689cc655685/0/10/SC/%/%/add_two_ints_client/%add_two_ints/"
    f"example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}/::,10:,:,:,,",
]


@pytest.mark.parametrize(("parts", "key"), DOC_KEYS)
def test_data_keys_are_the_documented_ones(parts: tuple[int, str, str, str], key: str) -> None:
    assert names.data_key(*parts) == key
    assert names.parse_data_key(key) == parts


@pytest.mark.parametrize("token", DOC_TOKENS)
def test_documented_tokens_parse_and_rebuild_byte_for_byte(token: str) -> None:
    entity = names.parse_token(token)
    assert entity.token() == token


def test_documented_talker_token_reads_as_its_parts() -> None:
    entity = names.parse_token(DOC_TOKENS[2])
    assert (entity.domain, entity.session_id, entity.node_id, entity.entity_id) == (2, "8b20917502ee955ac4476e0266340d5c", 0, 10)
    assert entity.kind is EntityKind.PUBLISHER
    assert (entity.namespace, entity.node_name, entity.node, entity.enclave) == ("/", "talker", "/talker", "/")
    assert (entity.topic, entity.ros_type, entity.type_hash) == ("/chatter", "std_msgs/msg/String", STRING_HASH)
    assert entity.qos == QoS(depth=7)


@pytest.mark.parametrize(
    ("qos", "text"),
    [
        (QoS(), "::,10:,:,:,,"),  # rclcpp's default depth of 10; everything else rmw_zenoh's default
        (QoS(depth=42), "::,:,:,:,,"),  # rmw_zenoh's own default depth is elided too
        (QoS(Reliability.BEST_EFFORT, depth=5), "2::,5:,:,:,,"),
        (QoS(durability=Durability.TRANSIENT_LOCAL, depth=1), ":1:,1:,:,:,,"),
        (QoS(keep_all=True), "::2,10:,:,:,,"),
    ],
)
def test_qos_strings(qos: QoS, text: str) -> None:
    assert qos.encode() == text
    assert QoS.decode(text) == qos


def test_a_namespaced_node_is_mangled_and_demangled() -> None:
    entity = Entity(
        0,
        "1234abcd",
        0,
        3,
        EntityKind.PUBLISHER,
        "/robot1/arm",
        "camera",
        "/",
        "/robot1/arm/image",
        "sensor_msgs/msg/Image",
        STRING_HASH,
        QoS(),
    )
    token = entity.token()
    assert "/%robot1%arm/camera/%robot1%arm%image/sensor_msgs::msg::dds_::Image_/" in token
    assert names.parse_token(token) == entity
    assert entity.node == "/robot1/arm/camera"


def test_the_humble_hash_is_accepted() -> None:
    key = names.data_key(0, "/chatter", "std_msgs/msg/String", names.HASH_NOT_SUPPORTED)
    assert key == "0/chatter/std_msgs::msg::dds_::String_/TypeHashNotSupported"
    assert names.parse_data_key(key)[3] == names.HASH_NOT_SUPPORTED


def test_type_names_map_both_ways() -> None:
    assert names.dds_type_name("sensor_msgs/msg/CompressedImage") == "sensor_msgs::msg::dds_::CompressedImage_"
    assert names.ros_type_name("sensor_msgs::msg::dds_::CompressedImage_") == "sensor_msgs/msg/CompressedImage"


def test_the_gid_is_xxh3_128_of_the_token_low_half_first() -> None:
    # XXH3_128bits("") = 99aa06d3014798d8_6001c324468d497f (xxHash's sanity vector): rmw_zenoh
    # copies the low 64 bits then the high 64 bits, each as the machine (little-endian) holds them
    assert names.entity_gid("") == bytes.fromhex("7f498d4624c30160") + bytes.fromhex("d8984701d306aa99")
    entity = names.parse_token(DOC_TOKENS[2])
    assert len(entity.gid()) == 16 and entity.gid() == names.entity_gid(DOC_TOKENS[2])


@pytest.mark.parametrize(
    "topic",
    ["chatter", "/", "/chatter/", "//chatter", "/9lives", "/a b", "/a/*", "/" + "x" * 600, "/ü"],
)
def test_bad_topics_are_refused(topic: str) -> None:
    with pytest.raises(BindingError, match="topic|part"):
        names.check_topic(topic)


@pytest.mark.parametrize(
    ("token", "problem"),
    [
        ("@ros2_lv/0/abc/0/0/NN/%/%", "9 or 13 parts"),
        ("@other/0/abc/0/0/NN/%/%/n", "9 or 13 parts"),
        ("@ros2_lv/x/abc/0/0/NN/%/%/n", "domain"),
        ("@ros2_lv/0/abc/0/0/XX/%/%/n", "entity kind"),
        ("@ros2_lv/0/abc/0/0/NN/%/%/n/extra", "node token of 10 parts"),
        (f"@ros2_lv/0/abc/0/1/MP/%/%/n/%t/std_msgs::msg::dds_::String_/{STRING_HASH}", "13"),
        ("@ros2_lv/0/abc/0/1/MP/%/%/n/%t/std_msgs::msg::dds_::String_/RIHS01_zz/::,10:,:,:,,", "type hash"),
        (f"@ros2_lv/0/abc/0/1/MP/%/%/n/%t/String/{STRING_HASH}/::,10:,:,:,,", "type"),
        (f"@ros2_lv/0/abc/0/1/MP/%/%/n/%t/std_msgs::msg::dds_::String_/{STRING_HASH}/::,x:,:,:,,", "QoS"),
        (f"@ros2_lv/0/abc/0/1/MP/%/%/n/%t/std_msgs::msg::dds_::String_/{STRING_HASH}/9::,1:,:,:,,", "QoS"),
        ("@ros2_lv/0/" + "a" * 3000, "bytes"),
    ],
)
def test_malformed_tokens_are_refused_naming_the_part(token: str, problem: str) -> None:
    with pytest.raises(BindingError, match=problem):
        names.parse_token(token)


@pytest.mark.parametrize("key", ["chatter/std_msgs::msg::dds_::String_/h", "0/std_msgs::msg::dds_::String_/" + STRING_HASH, "0/a/b/c"])
def test_malformed_data_keys_are_refused(key: str) -> None:
    with pytest.raises(BindingError):
        names.parse_data_key(key)
