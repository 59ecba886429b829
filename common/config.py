"""Service settings: one frozen dataclass per service, a TOML file first, flags over it.

``load_settings(SimSettings, path, overrides)`` reads the file (if any), rejects unknown
keys and wrong types naming the key, then applies the non-``None`` overrides (the CLI
flags). A field may declare ``metadata={"choices": (...)}`` and ``{"min": x}``; both are
checked at load. Tuples accept TOML arrays or comma-separated strings.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from common.errors import ConfigError

T = TypeVar("T")


def _coerce(key: str, value: Any, annotation: Any) -> Any:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(key, value, inner[0])
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in {"true", "false", "1", "0", "yes", "no"}:
            return value.lower() in {"true", "1", "yes"}
        raise ConfigError(f"setting {key!r}: expected true/false, got {value!r}")
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise ConfigError(f"setting {key!r}: expected an integer, got {value!r}")
        try:
            return int(value)
        except ValueError:
            raise ConfigError(f"setting {key!r}: expected an integer, got {value!r}") from None
    if annotation is float:
        if isinstance(value, bool):
            raise ConfigError(f"setting {key!r}: expected a number, got {value!r}")
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"setting {key!r}: expected a number, got {value!r}") from None
        if number != number or number in (float("inf"), float("-inf")):
            raise ConfigError(f"setting {key!r}: expected a finite number, got {value!r}")
        return number
    if annotation is str:
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise ConfigError(f"setting {key!r}: expected a string, got {value!r}")
        return str(value)
    if origin is tuple:
        items: Any = value
        if isinstance(value, str):
            items = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(items, (list, tuple)):
            raise ConfigError(f"setting {key!r}: expected a list, got {value!r}")
        item_type = args[0] if args else str
        return tuple(_coerce(key, v, item_type) for v in items)
    return value


def read_toml(path: str | Path, *, what: str = "config file") -> dict[str, Any]:
    """A TOML file as a dict; ConfigError naming ``what`` and the file if missing or bad."""
    p = Path(path)
    try:
        return tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{what} {p} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{what} {p} is not valid TOML: {exc}") from None


def load_settings(cls: type[T], path: str | Path | None = None,
                  overrides: Mapping[str, Any] | None = None) -> T:
    """Build ``cls`` from a TOML file and flag overrides (see module docstring)."""
    values: dict[str, Any] = read_toml(path) if path else {}
    for key, value in (overrides or {}).items():
        if value is not None:
            values[key.replace("-", "_")] = value
    return settings_from_mapping(cls, values, source=str(path) if path else "flags")


def settings_from_mapping(cls: type[T], values: Mapping[str, Any], *, source: str = "") -> T:
    """Validate a plain mapping into ``cls`` (unknown keys and bad values rejected)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(values) - set(fields))
    if unknown:
        where = f" in {source}" if source else ""
        raise ConfigError(f"unknown setting(s){where}: {', '.join(unknown)}; "
                          f"known: {', '.join(sorted(fields))}")
    kwargs = {}
    for key, value in values.items():
        f = fields[key]
        coerced = _coerce(key, value, hints[key])
        choices = f.metadata.get("choices")
        if choices is not None and coerced not in choices:
            raise ConfigError(f"setting {key!r}: {coerced!r} is not one of {list(choices)}")
        minimum = f.metadata.get("min")
        if minimum is not None and coerced is not None and coerced < minimum:
            raise ConfigError(f"setting {key!r}: {coerced!r} is below the minimum {minimum}")
        kwargs[key] = coerced
    return cls(**kwargs)
