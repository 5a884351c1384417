"""Writing ROS 2 MCAP bags: profile ``ros2``, ``ros2msg`` schemas, ``cdr`` messages, zstd chunks.

The files are what rosbag2's MCAP plugin writes (channel metadata ``offered_qos_profiles`` and
``topic_type_hash``, the RIHS01 hash of the type), minus its own ``rosbag2`` metadata record: rosbags,
the mcap tools, Foxglove and ``ros2 bag`` read them. ``Rosbag2Writer`` writes a rosbag2 bag directory
instead (``metadata.yaml`` + ``<name>_0.mcap`` with that record), what ``ros2 bag record -s mcap`` makes.
Messages go in as rclpy message objects (serialized here) or as raw CDR bytes with their type name;
schemas and channels are registered on first use. With ``canonical=True`` (default) serialized objects
get zeroed padding bytes (``schemas.canonical_cdr``), so the same input always gives the same file.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any, BinaryIO

import yaml
from mcap.writer import CompressionType, Writer

from monovoc_ros import __version__
from monovoc_ros.bags import schemas
from monovoc_ros.bags.qos import OFFERED_QOS_KEY, OfferedQos, qos_items, qos_yaml

PROFILE = "ros2"
LIBRARY = f"monovoc_ros-{__version__}"  # no timestamps or host names: output must be reproducible
DEFAULT_CHUNK_SIZE = 4 * 1024 * 1024


class BagWriter:
    """An MCAP bag being written; use as a context manager (or call ``finish()``) so the file is finalized.

    Not thread-safe: callers that write from several threads (the recorder) hold their own lock.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        compression: str = "zstd",
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        canonical: bool = True,
        library: str = LIBRARY,
    ) -> None:
        if compression not in ("zstd", "lz4", "none"):
            raise ValueError(f"compression must be zstd, lz4 or none, got {compression!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.canonical = canonical
        self._file: BinaryIO = open(self.path, "wb")
        self._writer = Writer(
            self._file,
            chunk_size=chunk_size,
            compression={"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[
                compression
            ],
        )
        self._writer.start(profile=PROFILE, library=library)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, type name)
        self.qos: dict[str, list[OfferedQos]] = {}  # topic -> offered profiles, as registered
        self.counts: dict[str, int] = {}
        self.start_ns: int | None = None  # first and last log time written
        self.end_ns: int | None = None
        self.finished = False

    # --------------------------------------------------------------------------------- registration

    def add_topic(self, topic: str, type_name: str, qos: list[OfferedQos] | OfferedQos | None = None) -> int:
        """Registers ``topic`` (idempotent); ``qos`` becomes rosbag2's ``offered_qos_profiles``, and the
        type's RIHS01 hash its ``topic_type_hash``."""
        type_name = schemas.normalize_type_name(type_name)
        if topic in self._channels:
            channel_id, known = self._channels[topic]
            if known != type_name:
                raise ValueError(f"{topic}: already registered as {known}, cannot write {type_name}")
            return channel_id
        if type_name not in self._schemas:
            self._schemas[type_name] = self._writer.register_schema(
                name=type_name,
                encoding=schemas.SCHEMA_ENCODING,
                data=schemas.message_definition(type_name).encode(),
            )
        profiles = [qos] if isinstance(qos, OfferedQos) else list(qos or [OfferedQos()])
        channel_id = self._writer.register_channel(
            topic=topic,
            message_encoding=schemas.MESSAGE_ENCODING,
            schema_id=self._schemas[type_name],
            metadata={OFFERED_QOS_KEY: qos_yaml(profiles), schemas.TYPE_HASH_KEY: schemas.type_hash(type_name)},
        )
        self._channels[topic] = (channel_id, type_name)
        self.qos[topic] = profiles
        self.counts[topic] = 0
        return channel_id

    # -------------------------------------------------------------------------------------- writing

    def write(
        self,
        topic: str,
        message: Any,
        log_time_ns: int,
        *,
        type_name: str | None = None,
        publish_time_ns: int | None = None,
        qos: list[OfferedQos] | OfferedQos | None = None,
    ) -> None:
        """Writes an rclpy message object, or raw CDR ``bytes`` (then ``type_name`` is required
        unless the topic is registered)."""
        if isinstance(message, bytes | bytearray | memoryview):
            data = bytes(message)
            if type_name is None:
                if topic not in self._channels:
                    raise ValueError(f"{topic}: raw CDR needs a type_name on the topic's first message")
                type_name = self._channels[topic][1]
        else:
            from rclpy.serialization import serialize_message

            type_name = type_name or schemas.type_name_of(message)
            data = serialize_message(message)
            if self.canonical:
                data = schemas.canonical_cdr(data, type_name)
        if int(log_time_ns) < 0:
            raise ValueError(f"{topic}: log time {log_time_ns} is negative")
        channel_id = self.add_topic(topic, type_name, qos)
        log_time = int(log_time_ns)
        publish_time = log_time if publish_time_ns is None else int(publish_time_ns)
        self._writer.add_message(
            channel_id, log_time=log_time, publish_time=publish_time, data=data, sequence=self.counts[topic]
        )
        self.counts[topic] += 1
        self.start_ns = log_time if self.start_ns is None else min(self.start_ns, log_time)
        self.end_ns = log_time if self.end_ns is None else max(self.end_ns, log_time)

    def topics(self) -> dict[str, str]:
        """Registered topics -> type names, in registration order."""
        return {topic: type_name for topic, (_, type_name) in self._channels.items()}

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        """An MCAP metadata record (string -> string map)."""
        self._writer.add_metadata(name, {str(k): str(v) for k, v in values.items()})

    def add_json_metadata(self, name: str, value: Any) -> None:
        """A metadata record holding ``value`` as JSON under the key ``json`` (read with ``reader.bag_metadata``)."""
        self.add_metadata(name, {"json": json.dumps(value, sort_keys=True)})

    def finish(self) -> None:
        """Writes the summary and closes the file; safe to call twice."""
        if self.finished:
            return
        self.finished = True
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.finish()


ROSBAG2_VERSION = 9  # the metadata.yaml version rosbag2 Jazzy writes
ROSBAG2_METADATA = "metadata.yaml"


class Rosbag2Writer(BagWriter):
    """A rosbag2 bag directory: ``DIR/metadata.yaml`` and ``DIR/<DIR name>_0.mcap`` (one file, no splitting).

    ``finish()`` adds the ``rosbag2`` metadata record to the MCAP file (as rosbag2's MCAP plugin does)
    and then writes ``metadata.yaml`` (atomically); rosbags' ``rosbag2.Reader`` and ``ros2 bag``
    open the directory. Like ``ros2 bag record``, refuses a directory that already exists.

    Not rosbags' ``rosbag2.Writer``: its MCAP storage (rosbags 0.11) records no ``topic_type_hash`` per
    channel, writes every message's publish time as its log time, offers neither lz4 nor a chunk size, and
    names the file ``<DIR name>.mcap`` with ``ros_distro: rosbags``; this bag is what ``ros2 bag record``
    writes.
    """

    def __init__(self, directory: str | os.PathLike, **kwargs: Any) -> None:
        self.directory = Path(directory)
        if self.directory.exists():
            raise ValueError(f"{self.directory}: already exists (a rosbag2 bag is written to a new directory)")
        self.directory.mkdir(parents=True)
        try:
            super().__init__(self.directory / f"{self.directory.name}_0.mcap", **kwargs)
        except BaseException:
            shutil.rmtree(self.directory, ignore_errors=True)
            raise

    def metadata(self) -> dict:
        """The ``rosbag2_bagfile_information`` of what was written so far (rosbag2 Jazzy, version 9)."""
        start = self.start_ns or 0
        duration = 0 if self.start_ns is None else self.end_ns - self.start_ns
        total = sum(self.counts.values())
        return {
            "version": ROSBAG2_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": total,
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": topic,
                        "type": type_name,
                        "serialization_format": schemas.MESSAGE_ENCODING,
                        "offered_qos_profiles": qos_items(self.qos[topic]),
                        "type_description_hash": schemas.type_hash(type_name),
                    },
                    "message_count": self.counts[topic],
                }
                for topic, type_name in self.topics().items()
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.path.name],
            "files": [
                {
                    "path": self.path.name,
                    "starting_time": {"nanoseconds_since_epoch": start},
                    "duration": {"nanoseconds": duration},
                    "message_count": total,
                }
            ],
            "custom_data": None,
            "ros_distro": "jazzy",
        }

    def finish(self) -> None:
        if self.finished:
            return
        info = self.metadata()
        self.add_metadata("rosbag2", {"serialized_metadata": yaml.safe_dump(info, sort_keys=False)})
        super().finish()
        tmp = self.directory / (ROSBAG2_METADATA + ".tmp")
        tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False))
        os.replace(tmp, self.directory / ROSBAG2_METADATA)
