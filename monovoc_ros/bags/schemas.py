"""ROS 2 message types by name: rclpy classes, full ``ros2msg`` schemas, and canonical CDR.

A bag's schema for a type is its message definition followed by every type it depends on, in the
``ros2msg`` format rosbag2 writes (``====`` separators, ``MSG: pkg/Type`` headers). The definitions come
from rosbags' stock Jazzy typestore; types it does not know (``monovoc_interfaces``, anything else
installed) are registered from their ``.msg`` files under ``share/`` of the ament prefixes (the venv
here, ``/opt/ros/jazzy`` on a robot), dependencies first.

``type_hash`` gives a type's RIHS01 type-description hash (what rclpy advertises for an endpoint and
rosbag2 Jazzy stores per channel as ``topic_type_hash``): from the ``.json`` type description that
rosidl generates next to each ``.msg`` under ``share/``, else computed by rosbags from the definition
(the two agree for every type used here; tests compare both with a live publisher's hash).

rclpy's serializer leaves CDR alignment padding uninitialized, so the same message can serialize to
different bytes. ``canonical_cdr`` re-serializes through rosbags (zeroed padding, ~4 ms for an 8 MB
cloud), which makes converted bags byte-for-byte reproducible.
"""

from __future__ import annotations

import functools
import importlib
import json
import os
import sys
import threading
from pathlib import Path
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
TYPE_HASH_KEY = "topic_type_hash"  # MCAP channel metadata key of rosbag2 Jazzy (RIHS01_<sha256 hex>)
_LOCK = threading.RLock()  # the typestore is shared by recorder callbacks


class UnknownTypeError(LookupError):
    """A message type with no definition in the typestore nor in any ament prefix's share/."""


def normalize_type_name(name: str) -> str:
    """``pkg/msg/Type`` for ``pkg/msg/Type``, ``pkg/Type`` or ``pkg.msg.Type``."""
    parts = [p for p in name.replace(".", "/").split("/") if p]
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3:
        return "/".join(parts)
    raise ValueError(f"not a ROS message type name: {name!r} (expected pkg/msg/Type)")


def type_name_of(msg: Any) -> str:
    """``pkg/msg/Type`` of an rclpy message object or class."""
    cls = msg if isinstance(msg, type) else type(msg)
    package, kind = cls.__module__.split(".")[:2]  # e.g. sensor_msgs.msg._image
    return f"{package}/{kind}/{cls.__name__}"


def message_class(type_name: str) -> type:
    """The rclpy message class of ``pkg/msg/Type`` (its generated Python package must be installed)."""
    package, kind, name = normalize_type_name(type_name).split("/")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError):
        raise UnknownTypeError(f"no rclpy message class for {type_name!r}: is {package} installed?") from None


def _share_dirs() -> list[Path]:
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)  # the venv's own share/, also when AMENT_PREFIX_PATH is unset
    seen: list[Path] = []
    for prefix in prefixes:
        share = Path(prefix) / "share"
        if share.is_dir() and share not in seen:
            seen.append(share)
    return seen


def _msg_file(type_name: str) -> Path:
    package, kind, name = type_name.split("/")
    for share in _share_dirs():
        path = share / package / kind / f"{name}.msg"
        if path.is_file():
            return path
    raise UnknownTypeError(
        f"{type_name}: not in the Jazzy typestore and no {package}/{kind}/{name}.msg under "
        f"{[str(s) for s in _share_dirs()]}"
    )


def _referenced(desc: tuple) -> list[str]:
    # Field descriptions nest (NAME, 'pkg/msg/T'), (ARRAY|SEQUENCE, (inner, size)) and (BASE, ...).
    kind, rest = desc
    if kind == Nodetype.NAME:
        return [rest]
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return _referenced(rest[0])
    return []


@functools.cache
def typestore():
    """The process-wide rosbags typestore (stock Jazzy plus whatever was registered from share/)."""
    return get_typestore(Stores.ROS2_JAZZY)


def ensure_registered(type_name: str) -> str:
    """Makes ``type_name`` and its dependencies known to ``typestore()``; returns the normalized name."""
    type_name = normalize_type_name(type_name)
    with _LOCK:
        store = typestore()
        if type_name not in store.fielddefs:
            _register(store, type_name, set())
    return type_name


def _register(store, type_name: str, visiting: set[str]) -> None:
    if type_name in store.fielddefs or type_name in visiting:
        return
    visiting.add(type_name)
    types = get_types_from_msg(_msg_file(type_name).read_text(), type_name)
    for _, fields in types.values():
        for _, desc in fields:
            for dep in _referenced(desc):
                _register(store, dep, visiting)
    store.register(types)


@functools.cache
def message_definition(type_name: str) -> str:
    """The full ``ros2msg`` schema text of ``type_name`` (with every dependency)."""
    type_name = ensure_registered(type_name)
    with _LOCK:
        text, _ = typestore().generate_msgdef(type_name, ros_version=2)
    return text


@functools.cache
def type_hash(type_name: str) -> str:
    """``RIHS01_<64 hex>`` of ``pkg/msg/Type`` (see the module docstring for where it comes from)."""
    type_name = normalize_type_name(type_name)
    package, kind, name = type_name.split("/")
    for share in _share_dirs():
        path = share / package / kind / f"{name}.json"
        if path.is_file():
            try:
                hashes = json.loads(path.read_text())["type_hashes"]
                return next(h["hash_string"] for h in hashes if h["type_name"] == type_name)
            except (ValueError, KeyError, TypeError, StopIteration):
                break  # an unreadable description: compute the hash instead
    type_name = ensure_registered(type_name)
    with _LOCK:
        return typestore().hash_rihs01(type_name)


def canonical_cdr(data: bytes, type_name: str) -> bytes:
    """``data`` re-serialized by rosbags: the same content with deterministic (zero) padding bytes."""
    type_name = ensure_registered(type_name)
    return bytes(typestore().serialize_cdr(deserialize_rosbags(data, type_name), type_name))


def deserialize_rosbags(data: bytes | memoryview, type_name: str) -> Any:
    """``data`` decoded by rosbags (dataclasses; byte arrays as read-only NumPy views of ``data``)."""
    type_name = ensure_registered(type_name)
    # A memoryview: rosbags slices off the encapsulation header, which on bytes copies the payload (57 MB for a
    # 1M-Gaussian map: ~45 ms).
    return typestore().deserialize_cdr(memoryview(data), type_name)
