"""Settings declared once: a dataclass field gives the TOML key, its checks, its flag and docs.

Every service has one frozen settings dataclass. Each field is declared with
:func:`setting`, which records what a reader needs (doc, unit, bounds, choices) and how
the command line spells it::

    rate: float = setting(1.0, doc="× real time; 0 = as fast as possible", min=0.0)
    hold_s: float = setting(0.0, doc="seconds standing still first", unit="s", flag="--hold")
    wait_for_estimator: bool = setting(True, doc="wait for an estimator", flag="--no-wait")
    path: str = setting("", doc="dataset folder", positional=True, required=True)

From that one line come the TOML key (the field name), the checks at load
(:func:`load_settings`: type, ``choices``, ``min``/``max``, ``required``; unknown keys are
rejected naming the key), the flag with its help (:func:`add_flags`: ``--rate RATE``, help
"× real time; 0 = as fast as possible (default: 1; ≥ 0)") and its row in docs/cli.md.

Flags are ``--`` + the field name with ``-`` for ``_`` unless ``flag`` names them
(``flag=False``: TOML only). A ``bool`` is a switch: ``--x`` sets it when it defaults to
false, ``--no-x`` clears it when it defaults to true. ``action="count"`` / ``"append"``
give ``-v -v`` and repeatable flags. A flag that is not given leaves the file's (or the
default) value: flags are parsed with no default of their own.

Values from TOML or flags are coerced to the annotation: ``bool`` accepts true/false/1/0/
yes/no, tuples accept TOML arrays or comma-separated strings (a fixed-length tuple checks
its length), a nested settings dataclass accepts a TOML table. Plain dataclass fields with
``metadata={"doc": …, "min": …, "choices": …}`` are understood too.
"""

from __future__ import annotations

import argparse
import dataclasses
import tomllib
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from slamlens.common.errors import ConfigError

T = TypeVar("T")

_ACTIONS = ("", "count", "append")


@dataclass(frozen=True)
class Setting:
    """What :func:`setting` records about one field (``metadata["setting"]``)."""

    doc: str = ""  #: what it means; a ``bool``'s doc says what ``true`` does
    unit: str = ""  #: shown after the default: "m", "s", "Hz", "m/s" …
    min: float | None = None  #: smallest value allowed (inclusive)
    max: float | None = None  #: largest value allowed (inclusive)
    choices: tuple[Any, ...] | None = None  #: the only values allowed
    flag: str | bool = True  #: True: derived name; "--name": that name; False: TOML only
    short: str = ""  #: a one-letter alias such as "-o"
    metavar: str = ""  #: the value's name in help ("FILE", "X,Y,Z"); derived if empty
    action: str = ""  #: "" (a value, or a switch for bool), "count" or "append"
    positional: bool = False  #: a positional argument instead of a flag
    required: bool = False  #: must be given by a flag or the file (an empty value is not)
    hidden: bool = False  #: a working flag left out of --help and docs/cli.md
    group: str = ""  #: --help section; empty = the command's settings section


def setting(default: Any = dataclasses.MISSING, *, doc: str, unit: str = "",
            min: float | None = None, max: float | None = None,
            choices: Sequence[Any] | None = None, flag: str | bool = True, short: str = "",
            metavar: str = "", action: str = "", positional: bool = False,
            required: bool = False, hidden: bool = False, group: str = "",
            default_factory: Any = dataclasses.MISSING) -> Any:
    """A dataclass field that is a setting: TOML key, validation, flag and docs in one.

    See the module docstring; every keyword is a :class:`Setting` attribute.
    """
    if action not in _ACTIONS:
        raise ConfigError(f"setting action {action!r} is not one of {list(_ACTIONS)}")
    spec = Setting(doc=doc, unit=unit, min=min, max=max,
                   choices=tuple(choices) if choices is not None else None, flag=flag,
                   short=short, metavar=metavar, action=action, positional=positional,
                   required=required, hidden=hidden, group=group)
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata={"setting": spec})
    return dataclasses.field(default=default, metadata={"setting": spec})


def spec_of(f: dataclasses.Field) -> Setting:
    """The :class:`Setting` of a field (built from plain ``metadata`` keys if need be)."""
    spec = f.metadata.get("setting")
    if isinstance(spec, Setting):
        return spec
    choices = f.metadata.get("choices")
    return Setting(doc=str(f.metadata.get("doc", "")), min=f.metadata.get("min"),
                   max=f.metadata.get("max"),
                   choices=tuple(choices) if choices is not None else None)


def default_of(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


# -------------------------------------------------------------------------- validation


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
        fixed = bool(args) and Ellipsis not in args
        if fixed and len(items) != len(args):
            raise ConfigError(f"setting {key!r}: expected {len(args)} values, got "
                              f"{len(items)} ({value!r})")
        item_types = args if fixed else (args[0] if args else str,) * len(items)
        return tuple(_coerce(key, v, t) for v, t in zip(items, item_types, strict=True))
    if dataclasses.is_dataclass(annotation) and isinstance(annotation, type):
        if isinstance(value, annotation):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(f"setting {key!r}: expected a table of "
                              f"{annotation.__name__} settings, got {value!r}")
        return settings_from_mapping(annotation, value, source=f"[{key}]")
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
    """Build ``cls`` from a TOML file and flag overrides (``None`` overrides are not given)."""
    values: dict[str, Any] = read_toml(path) if path else {}
    for key, value in (overrides or {}).items():
        if value is not None:
            values[key.replace("-", "_")] = value
    return settings_from_mapping(cls, values, source=str(path) if path else "flags")


def _checked(key: str, value: Any, f: dataclasses.Field, hint: Any) -> Any:
    """``value`` coerced to the field's type and checked against its choices and bounds."""
    spec = spec_of(f)
    coerced = _coerce(key, value, hint)
    if spec.choices is not None and coerced not in spec.choices:
        raise ConfigError(f"setting {key!r}: {coerced!r} is not one of {list(spec.choices)}")
    if spec.min is not None and coerced is not None and coerced < spec.min:
        raise ConfigError(f"setting {key!r}: {coerced!r} is below the minimum {spec.min}")
    if spec.max is not None and coerced is not None and coerced > spec.max:
        raise ConfigError(f"setting {key!r}: {coerced!r} is above the maximum {spec.max}")
    return coerced


def check_value(cls: type, key: str, value: Any) -> Any:
    """One setting of ``cls`` checked alone (type, choices, bounds): its coerced value.

    For a part of the settings given somewhere else (a launch file's service table);
    required fields and cross-field checks are the whole settings' (:func:`load_settings`).
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    if key not in fields:
        raise ConfigError(f"unknown setting {key!r}; known: {', '.join(sorted(fields))}")
    return _checked(key, value, fields[key], typing.get_type_hints(cls)[key])


def settings_from_mapping(cls: type[T], values: Mapping[str, Any], *, source: str = "") -> T:
    """Validate a plain mapping into ``cls`` (unknown keys and bad values rejected)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(values) - set(fields))
    if unknown:
        where = f" in {source}" if source else ""
        raise ConfigError(f"unknown setting(s){where}: {', '.join(unknown)}; "
                          f"known: {', '.join(sorted(fields))}")
    kwargs = {key: _checked(key, value, fields[key], hints[key])
              for key, value in values.items()}
    for key, f in fields.items():
        spec = spec_of(f)
        if spec.required and kwargs.get(key, default_of(f)) in ("", (), None):
            given = metavar_of(f) if spec.positional else (flag_names(f) or [key])[-1]
            raise ConfigError(f"setting {key!r} is required: give {given} or {key} = … in "
                              f"the --config file ({spec.doc})")
    return cls(**kwargs)


# ---------------------------------------------------------------------- command line


def flag_names(f: dataclasses.Field) -> list[str]:
    """The option strings of a field's flag (``[]`` for TOML-only; the name if positional)."""
    spec = spec_of(f)
    if spec.positional:
        return [f.name]
    if spec.flag is False:
        return []
    if isinstance(spec.flag, str):
        name = spec.flag
    elif isinstance(f.default, bool) and f.default and not spec.action:
        name = "--no-" + f.name.replace("_", "-")
    else:
        name = "--" + f.name.replace("_", "-")
    return [spec.short, name] if spec.short else [name]


def _is_switch(f: dataclasses.Field, hint: Any) -> bool:
    return hint is bool and not spec_of(f).action and not spec_of(f).positional


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, tuple):
        return ",".join(_fmt(v) for v in value) if value else "none"
    if value == "":
        return "empty"
    return "none" if value is None else str(value)


def describe(f: dataclasses.Field, *, as_flag: bool = False) -> str:
    """A setting's doc, then its default (with unit), bounds and whether it is required.

    ``as_flag``: the text of its flag, which for a ``--no-x`` switch says "do not …".
    """
    spec = spec_of(f)
    doc = spec.doc
    if as_flag and f.default is True and not spec.action and spec.flag is not False:
        doc = f"do not {doc}"  # the flag is the --no-x switch
    parts = []
    default = default_of(f)
    if spec.required:
        parts.append("required")
    elif not (isinstance(default, bool) or spec.action or dataclasses.is_dataclass(default)):
        parts.append(f"default: {_fmt(default)}" + (f" {spec.unit}" if spec.unit else ""))
    elif spec.unit:
        parts.append(spec.unit)
    if spec.min is not None and spec.max is not None:
        parts.append(f"{_fmt(spec.min)} … {_fmt(spec.max)}")
    elif spec.min is not None:
        parts.append(f"≥ {_fmt(spec.min)}")
    elif spec.max is not None:
        parts.append(f"≤ {_fmt(spec.max)}")
    return f"{doc} ({'; '.join(parts)})" if parts else doc


def metavar_of(f: dataclasses.Field) -> str:
    spec = spec_of(f)
    if spec.metavar:
        return spec.metavar
    if spec.choices is not None:
        return "{" + ",".join(str(c) for c in spec.choices) + "}"
    names = flag_names(f)
    return names[-1].lstrip("-").replace("-", "_").upper() if names else f.name.upper()


def _value_type(hint: Any) -> Any:
    """``int`` / ``float`` for argparse to check early; anything else is coerced at load."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    base = args[0] if typing.get_origin(hint) in (typing.Union, types.UnionType) else hint
    return base if base in (int, float) else str


def add_flags(parser: argparse.ArgumentParser, cls: type, *, title: str = "settings",
              groups: dict[str, Any] | None = None) -> None:
    """Add one flag (or positional) per field of ``cls`` to ``parser``.

    Flags default to "not given" (argparse.SUPPRESS), so :func:`flag_values` returns only
    what the command line set; ``groups`` shares --help sections between calls.
    """
    hints = typing.get_type_hints(cls)
    groups = {} if groups is None else groups
    for f in dataclasses.fields(cls):
        names = flag_names(f)
        if not names:
            continue
        spec = spec_of(f)
        section = spec.group or title
        if section not in groups:
            groups[section] = parser.add_argument_group(section)
        group = groups[section]
        text = argparse.SUPPRESS if spec.hidden else describe(f, as_flag=True).replace("%", "%%")
        kwargs: dict[str, Any] = {"default": argparse.SUPPRESS, "help": text}
        if spec.positional:
            kwargs["nargs"] = "*" if typing.get_origin(hints[f.name]) is tuple else "?"
            kwargs["metavar"] = metavar_of(f)
            group.add_argument(f.name, **kwargs)
            continue
        kwargs["dest"] = f.name
        if _is_switch(f, hints[f.name]):
            kwargs["action"] = "store_false" if f.default is True else "store_true"
        elif spec.action == "count":
            kwargs["action"] = "count"
        else:
            if spec.action == "append":
                kwargs["action"] = "append"
            kwargs["metavar"] = metavar_of(f)
            kwargs["type"] = _value_type(hints[f.name])
        group.add_argument(*names, **kwargs)


def flag_values(cls: type, args: argparse.Namespace) -> dict[str, Any]:
    """The fields of ``cls`` that the command line set (see :func:`add_flags`)."""
    return {f.name: getattr(args, f.name) for f in dataclasses.fields(cls)
            if f.name in vars(args)}


def settings_from_args(cls: type[T], args: argparse.Namespace) -> T:
    """``cls`` from the ``--config`` file (if the command has one) with the flags over it."""
    return load_settings(cls, getattr(args, "config", None), flag_values(cls, args))
