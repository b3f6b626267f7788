"""Recording dyknow streams to MCAP files, and reading and replaying MCAP files from any writer.

============================  ===========================================================================
module                        what it holds
============================  ===========================================================================
:mod:`~.writer`               :class:`Recorder`: streams to an MCAP file, through ``mcap.writer.Writer``
:mod:`~.codecs`               payloads <-> MCAP message encodings and schemas (Foxglove images, JSON, ROS 2)
:mod:`~.protobuf`             the little of protobuf's wire format the codecs need
:mod:`~.reader`               :class:`Recording`: a file's summary, channels and messages in log-time order
:mod:`~.framing`              records read with every bound checked, and the damage found
:mod:`~.scan`                 the index of a file without a usable summary, and where it is damaged
:mod:`~.player`               :class:`Player`: replay into Zenoh or a callback; topics, keys and remapping
============================  ===========================================================================

Imports flow one way: ``protobuf <- codecs <- writer``; ``framing <- scan <- reader``;
``codecs, reader <- player``.
"""

from __future__ import annotations

from dyknow.errors import RecordingError
from dyknow.recording.codecs import COMPRESSED_IMAGE, NDARRAY, PAYLOAD_METADATA, PROTOBUF_SCHEMAS, RAW_IMAGE, image_array, image_encoding
from dyknow.recording.player import Player, key_for_topic
from dyknow.recording.reader import ChannelInfo, RecordedMessage, Recording, RecordingInfo
from dyknow.recording.writer import COMPRESSIONS, Recorder

__all__ = [
    "COMPRESSED_IMAGE",
    "COMPRESSIONS",
    "NDARRAY",
    "PAYLOAD_METADATA",
    "PROTOBUF_SCHEMAS",
    "RAW_IMAGE",
    "ChannelInfo",
    "Player",
    "RecordedMessage",
    "Recorder",
    "Recording",
    "RecordingError",
    "RecordingInfo",
    "image_array",
    "image_encoding",
    "key_for_topic",
]
