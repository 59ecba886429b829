"""Checking MCAP recordings in tests: the reader's validation and Foxglove schema decoding."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader


def protobuf_class(name: str, schema_data: bytes) -> Any:
    """The message class of ``name`` from a protobuf FileDescriptorSet (an MCAP schema)."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    pool = descriptor_pool.DescriptorPool()
    pending = list(fds.file)
    while pending:  # add each file after its dependencies
        left = []
        for fd in pending:
            try:
                pool.Add(fd)
            except (TypeError, KeyError):
                left.append(fd)
        if len(left) == len(pending):
            raise AssertionError(f"unresolvable protobuf schema {name}")
        pending = left
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def check_json(value: Any, schema: dict[str, Any], where: str = "$") -> None:
    """A minimal JSON Schema check (type, properties, required, items, additionalProperties)."""
    kinds = {"object": dict, "array": list, "string": str, "boolean": bool,
             "integer": int, "number": (int, float)}
    expected = schema.get("type")
    if expected is not None:
        assert isinstance(value, kinds[expected]), f"{where}: expected {expected}, got {value!r}"
        if expected in ("integer", "number"):
            assert not isinstance(value, bool), f"{where}: expected {expected}, got a bool"
    if isinstance(value, dict):
        for key in schema.get("required", []):
            assert key in value, f"{where}: required {key!r} missing"
        for key, sub in schema.get("properties", {}).items():
            if key in value:
                check_json(value[key], sub, f"{where}.{key}")
        extra = schema.get("additionalProperties")
        if isinstance(extra, dict):
            for key, v in value.items():
                if key not in schema.get("properties", {}):
                    check_json(v, extra, f"{where}.{key}")
    if isinstance(value, list) and "items" in schema:
        for i, v in enumerate(value):
            check_json(v, schema["items"], f"{where}[{i}]")


def validate(path: Path) -> dict[str, list[tuple[Any, Any]]]:
    """Validate a finished recording as the ``mcap`` package reads it: the summary is there,
    every chunk's CRC and the data section's CRC match, the message count agrees; every
    Foxglove channel decodes against its schema. Returns {topic: [(message, decoded)]}
    (decoded: the protobuf message or the JSON value; None for msgpack channels)."""
    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None, "no summary"
        assert summary.chunk_indexes, "no chunk index"
        decoders: dict[int, Any] = {}
        out: dict[str, list[tuple[Any, Any]]] = {}
        count = 0
        for schema, channel, message in reader.iter_messages():
            count += 1
            decoded = None
            if channel.message_encoding == "protobuf":
                assert schema is not None and schema.encoding == "protobuf"
                cls = decoders.get(schema.id)
                if cls is None:
                    cls = decoders[schema.id] = protobuf_class(schema.name, schema.data)
                decoded = cls.FromString(message.data)
            elif channel.message_encoding == "json":
                assert schema is not None and schema.encoding == "jsonschema"
                decoded = json.loads(message.data)
                check_json(decoded, json.loads(schema.data))
            else:
                assert channel.message_encoding == "msgpack" and channel.schema_id == 0
            out.setdefault(channel.topic, []).append((message, decoded))
        assert count == summary.statistics.message_count
    with path.open("rb") as f:  # the data section CRC, sequentially
        records = list(StreamReader(f, validate_crcs=True).records)
    assert records, "no records"
    return out


def layout_topics(layout: dict[str, Any]) -> set[str]:
    """Every topic a Foxglove layout (the app's export format) names: 3D and Image panels'
    topics, an Image panel's image and calibration, Plot series, a Table's topic."""
    topics: set[str] = set()
    for config in layout["configById"].values():
        topics.update(config.get("topics", {}))
        mode = config.get("imageMode", {})
        topics.update(mode[k] for k in ("imageTopic", "calibrationTopic") if k in mode)
        topics.update(series["value"].split(".", 1)[0] for series in config.get("paths", []))
        if "topicPath" in config:
            topics.add(config["topicPath"].split(".", 1)[0])
    return topics
