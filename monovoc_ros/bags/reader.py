"""Reading ROS 2 MCAP bags: raw CDR in log-time order, decoded on demand, plus a summary of the bag.

``iter_messages`` yields ``BagMessage``s, which unpack as ``(topic, type_name, log_time_ns, data)``;
``message.decode()`` turns the CDR into a message object with mcap_ros2's decoder (built from the
bag's own schema, so no generated code is needed). Any MCAP bag with ``cdr`` messages and ``ros2msg``
schemas works, not only ours (e.g. one written by ``ros2 bag record -s mcap``).
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from monovoc_ros.bags.qos import OFFERED_QOS_KEY, OfferedQos, parse_qos_yaml
from monovoc_ros.bags.schemas import TYPE_HASH_KEY

# What mcap raises on a file that ends inside a record (a recorder that died, a copy cut short): struct's error
# when fewer bytes are left than a record's fixed fields.
_CUT = (McapError, EOFError, ValueError, struct.error)


class BagError(ValueError):
    """A file that is not a readable ROS 2 MCAP bag; the message names the file."""


@dataclass(frozen=True, slots=True)
class BagMessage:
    topic: str
    type_name: str  # pkg/msg/Type (the schema name)
    log_time_ns: int
    data: bytes  # CDR, with its 4-byte encapsulation header
    publish_time_ns: int = 0
    encoding: str = "cdr"  # the channel's message encoding
    _decoder: Callable[[bytes], Any] | None = field(default=None, repr=False, compare=False)

    def __iter__(self) -> Iterator[Any]:
        return iter((self.topic, self.type_name, self.log_time_ns, self.data))

    def decode(self) -> Any:
        """The message as an object (mcap_ros2's dynamic class: attribute access like rclpy's)."""
        if self._decoder is None:
            raise BagError(f"{self.topic}: no ros2msg schema to decode {self.type_name} with")
        return self._decoder(self.data)


@dataclass
class TopicInfo:
    name: str
    type_name: str
    count: int
    qos: list[OfferedQos]  # offered_qos_profiles recorded with the channel (may be empty)
    type_hash: str = ""  # topic_type_hash recorded with the channel (RIHS01_...; "" when absent)

    @property
    def transient_local(self) -> bool:
        return any(q.transient_local for q in self.qos)


@dataclass
class BagInfo:
    path: Path
    size_bytes: int
    library: str
    profile: str
    topics: dict[str, TopicInfo]
    message_count: int
    start_ns: int | None
    end_ns: int | None
    compression: list[str]
    metadata: dict[str, dict[str, str]]
    finished: bool = True  # False: no summary/footer (read by a sequential scan)

    @property
    def duration_s(self) -> float:
        return 0.0 if self.start_ns is None else (self.end_ns - self.start_ns) / 1e9

    def as_dict(self) -> dict:
        """Plain values, for ``monovoc bag info --json``."""
        return {
            "path": str(self.path),
            "size_bytes": self.size_bytes,
            "library": self.library,
            "profile": self.profile,
            "messages": self.message_count,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "duration_s": round(self.duration_s, 6),
            "compression": self.compression,
            "finished": self.finished,
            "topics": {
                t.name: {"type": t.type_name, "count": t.count, "transient_local": t.transient_local}
                for t in self.topics.values()
            },
            "metadata": {name: sorted(values) for name, values in self.metadata.items()},
        }


def bag_file(path: str | os.PathLike) -> Path:
    """The MCAP file of ``path``: the file itself, or the one file of a rosbag2 bag directory
    (``metadata.yaml``'s ``relative_file_paths``, e.g. what ``monovoc record --format rosbag2`` writes)."""
    path = Path(path)
    if path.is_dir() and (path / "metadata.yaml").is_file():
        import yaml

        try:
            info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
            files = [path / f for f in info["relative_file_paths"]]
        except (yaml.YAMLError, OSError, KeyError, TypeError) as exc:
            raise BagError(f"{path}: unreadable metadata.yaml ({exc})") from None
        if len(files) != 1 or files[0].suffix != ".mcap":
            raise BagError(f"{path}: only rosbag2 bags of one .mcap file are supported, got {files}")
        path = files[0]
    if path.is_dir():
        raise BagError(f"{path}: a folder without a rosbag2 metadata.yaml, not a bag")
    if not path.is_file():
        raise BagError(f"{path}: no such bag file")
    return path


def _open(path: str | os.PathLike):
    path = bag_file(path)
    return path, open(path, "rb")


class _Decoders:
    """One mcap_ros2 decoder per schema, built on first use."""

    def __init__(self) -> None:
        self._factory = DecoderFactory()

    def for_channel(self, channel: Channel, schema: Schema | None) -> Callable[[bytes], Any] | None:
        try:
            return self._factory.decoder_for(channel.message_encoding, schema)
        except Exception as exc:  # mcap_ros2 raises its own errors on schemas it cannot parse
            name = schema.name if schema else "no schema"
            raise BagError(f"{channel.topic}: cannot build a decoder for {name}: {exc}") from exc


def _scan(f) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """Every complete message record from the start of the file, in file order (unfinished files)."""
    f.seek(0)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    try:
        for record in StreamReader(f).records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and record.channel_id in channels:
                channel = channels[record.channel_id]
                yield schemas.get(channel.schema_id), channel, record
    except _CUT:
        return  # the truncated tail (e.g. the chunk being written when the recorder died)


def _finished(reader) -> bool:
    try:
        reader.get_summary()
        return True
    except _CUT:
        return False


def iter_messages(
    path: str | os.PathLike,
    topics: Iterable[str] | None = None,
    *,
    start_ns: int | None = None,
    end_ns: int | None = None,
) -> Iterator[BagMessage]:
    """The bag's messages in log-time order (ties in file order), optionally only ``topics`` and
    ``start_ns <= log_time < end_ns``. Unfinished files: file order."""
    path, f = _open(path)
    decoders = _Decoders()
    lazy: dict[int, Callable[[bytes], Any] | None] = {}
    wanted = None if topics is None else set(topics)
    with f:
        try:
            reader = make_reader(f)
            if _finished(reader):
                messages = reader.iter_messages(
                    topics=list(wanted) if wanted is not None else None,
                    log_time_order=True,
                    starting_at=start_ns,
                    ending_before=end_ns,
                )
            else:
                messages = (
                    item
                    for item in _scan(f)
                    if (wanted is None or item[1].topic in wanted)
                    and (start_ns is None or item[2].log_time >= start_ns)
                    and (end_ns is None or item[2].log_time < end_ns)
                )
            for schema, channel, message in messages:
                if channel.id not in lazy:
                    lazy[channel.id] = _LazyDecoder(decoders, channel, schema)
                yield BagMessage(
                    channel.topic,
                    schema.name if schema else "",
                    message.log_time,
                    message.data,
                    message.publish_time,
                    channel.message_encoding,
                    lazy[channel.id],
                )
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f"{path}: not a readable MCAP bag ({type(exc).__name__}: {exc})") from exc


class _LazyDecoder:
    # Building a decoder parses the schema: only do it for topics whose messages get decoded.
    __slots__ = ("_args", "_decoders", "_fn")

    def __init__(self, decoders: _Decoders, channel: Channel, schema: Schema | None) -> None:
        self._decoders, self._args, self._fn = decoders, (channel, schema), None

    def __call__(self, data: bytes) -> Any:
        if self._fn is None:
            self._fn = self._decoders.for_channel(*self._args)
            if self._fn is None:
                channel, schema = self._args
                raise BagError(
                    f"{channel.topic}: cannot decode encoding {channel.message_encoding!r} "
                    f"with schema {schema.encoding if schema else None!r}"
                )
        return self._fn(data)


def bag_info(path: str | os.PathLike) -> BagInfo:
    """Topics, types, counts, time range and metadata, from the summary (or a scan of an unfinished file)."""
    path, f = _open(path)
    counts: dict[int, int] = {}
    start = end = None
    compression: set[str] = set()
    with f:
        try:
            reader = make_reader(f)
            header = reader.get_header()
            finished = _finished(reader)
            summary = reader.get_summary() if finished else None
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()} if finished else {}
        except Exception as exc:
            raise BagError(f"{path}: not a readable MCAP bag ({type(exc).__name__}: {exc})") from exc
        if summary is not None and summary.statistics is not None:
            counts = dict(summary.statistics.channel_message_counts)
            if summary.statistics.message_count:
                start, end = summary.statistics.message_start_time, summary.statistics.message_end_time
            compression = {c.compression or "none" for c in summary.chunk_indexes}
            channels, schemas = summary.channels, summary.schemas
        else:
            channels, schemas = {}, {}
            for schema, channel, message in _scan(f):
                channels[channel.id] = channel
                if schema is not None:
                    schemas[schema.id] = schema
                counts[channel.id] = counts.get(channel.id, 0) + 1
                start = message.log_time if start is None else min(start, message.log_time)
                end = message.log_time if end is None else max(end, message.log_time)
    topics: dict[str, TopicInfo] = {}
    for cid, channel in sorted(channels.items()):
        schema = schemas.get(channel.schema_id)
        qos = parse_qos_yaml(channel.metadata.get(OFFERED_QOS_KEY, ""))
        info = topics.get(channel.topic)
        if info is None:
            topics[channel.topic] = TopicInfo(
                channel.topic,
                schema.name if schema else "",
                counts.get(cid, 0),
                qos,
                channel.metadata.get(TYPE_HASH_KEY, ""),
            )
        else:  # several channels on one topic (e.g. two recordings merged)
            info.count += counts.get(cid, 0)
            info.qos += qos
    return BagInfo(
        path=path,
        size_bytes=path.stat().st_size,
        library=header.library,
        profile=header.profile,
        topics=topics,
        message_count=sum(t.count for t in topics.values()),
        start_ns=start,
        end_ns=end,
        compression=sorted(compression),
        metadata=metadata,
        finished=finished,
    )


def bag_metadata(path: str | os.PathLike, name: str) -> Any:
    """The JSON value of metadata record ``name`` written by ``BagWriter.add_json_metadata`` (None if absent)."""
    record = bag_info(path).metadata.get(name)
    if record is None or "json" not in record:
        return None
    return json.loads(record["json"])
