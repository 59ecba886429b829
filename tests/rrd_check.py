"""Reading a Rerun recording back in tests, with Rerun's own reader (``rerun.chunk``).

:func:`read_rrd` gives every row the file holds, per entity path, in the order they were
logged: the timeline values (``seq``, ``stamp`` …; none for static rows) and each
component column as plain Python (``"Ellipsoids3D:centers"`` → ``[[x, y, z], …]``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pyarrow as pa
from rerun.chunk import RrdReader

ROW_ID = "rerun.controls.RowId"


def read_rrd(path: Path) -> dict[str, list[dict[str, Any]]]:
    """{entity path: [row, …]} of the file's first recording (module docstring)."""
    rows: dict[str, list[tuple[bytes, dict[str, Any]]]] = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        columns = {}
        for name in batch.schema.names:
            column = batch.column(name)
            if pa.types.is_timestamp(column.type) or pa.types.is_duration(column.type):
                columns[name] = [None if v is None else v / 1e9 for v in
                                 column.cast(pa.int64()).to_pylist()]
            else:
                columns[name] = column.to_pylist()
        for i in range(batch.num_rows):
            row = {name: values[i] for name, values in columns.items()}
            rows.setdefault(chunk.entity_path, []).append((row.pop(ROW_ID), row))
    return {path: [row for _, row in sorted(entries, key=lambda e: e[0])]
            for path, entries in rows.items()}


def stores(path: Path) -> tuple[int, int]:
    """(recordings, blueprints) in the file."""
    reader = RrdReader(path)
    return len(reader.recordings()), len(reader.blueprints())
