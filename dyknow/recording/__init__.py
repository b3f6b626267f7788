"""Recording dyknow streams to MCAP files, and reading and replaying MCAP files from any writer.

==================  =====================================================================================
module              what it holds
==================  =====================================================================================
:mod:`~.writer`     :class:`Recorder`: streams to an MCAP file (through ``mcap.writer.Writer``)
:mod:`~.codecs`     payloads <-> MCAP message encodings and schemas: Foxglove images, JSON, ROS 2, text
:mod:`~.protobuf`   the little of protobuf's wire format that the codecs need
:mod:`~.reader`     :class:`Recording`: a file's summary, channels, messages in log-time order, records
:mod:`~.framing`    records and chunks read with every bound checked (:class:`ReadLimits`), and the :class:`~.framing.Damage`
:mod:`~.scan`       the index of a file without a usable summary, and where such a file is damaged
:mod:`~.player`     :class:`Player`: replay into Zenoh or a callback; the key of each topic, remapping
:mod:`~.offsets`    times of other clocks: the clock records beside the origins as stamped, and correcting them
==================  =====================================================================================

Imports flow one way: ``protobuf <- codecs <- writer``, ``framing <- scan <- reader``,
``codecs, reader <- player``, and ``offsets <- writer, player``.

What the ``mcap`` library does here, and what is ours (the details are in :mod:`~.reader`):

- **The library**: writing (``Writer``: chunks, compression, indexes, summary, CRCs); parsing
  every record (``mcap.records``); reading the summary of a file (``SeekingReader.get_summary``);
  the record stream the MCAP conformance suite checks (``StreamReader``, :meth:`Recording.records`);
  ROS 2 CDR decoding (``mcap_ros2``).
- **Ours**, because the library lacks it: reading a file it cannot (no summary or footer after a
  recorder was killed, truncation, corruption) chunk by chunk in log-time order, and with
  ``recover=True`` past the damage (:mod:`~.scan`); errors that name the file, the offset and
  what is wrong rather than ``EndOfFile()`` or ``struct.error`` (:mod:`~.framing`); checks the
  library skips (the closing magic, the summary's CRC, a chunk's compression and sizes, records
  running past their chunk or file, lengths that would make it allocate petabytes, chunks that
  decompress to gigabytes: :class:`ReadLimits`); and the
  log-time merge of chunks (:meth:`Recording.messages`), which is also three to four times faster
  than the library's for small messages.
"""

from __future__ import annotations

from dyknow.errors import RecordingError
from dyknow.recording.codecs import COMPRESSED_IMAGE, NDARRAY, PAYLOAD_METADATA, PROTOBUF_SCHEMAS, RAW_IMAGE, image_array, image_encoding
from dyknow.recording.offsets import CLOCK_METADATA, CLOCKS_TOPIC
from dyknow.recording.player import Player, key_for_topic
from dyknow.recording.reader import ChannelInfo, ReadLimits, RecordedMessage, Recording, RecordingInfo
from dyknow.recording.writer import COMPRESSIONS, Recorder

__all__ = [
    "CLOCKS_TOPIC",
    "CLOCK_METADATA",
    "COMPRESSED_IMAGE",
    "COMPRESSIONS",
    "NDARRAY",
    "PAYLOAD_METADATA",
    "PROTOBUF_SCHEMAS",
    "RAW_IMAGE",
    "ChannelInfo",
    "Player",
    "ReadLimits",
    "RecordedMessage",
    "Recorder",
    "Recording",
    "RecordingError",
    "RecordingInfo",
    "image_array",
    "image_encoding",
    "key_for_topic",
]
