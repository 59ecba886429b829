"""Launch files: a described group of slamlens services, checked before anything starts.

A launch file is TOML (deploy/robot.toml is an example; docs/launch.md the reference)::

    [launch]                      # optional: the group's own settings (LaunchOptions)
    respawn = true                # restart a service that fails, with back-off …
    respawn_max_s = 10.0          # … of at most this long

    [vars]                        # ${name} anywhere in a string below;
    robot = "robot1"              # `slamlens launch FILE --set robot=r2` overrides

    [defaults]                    # settings every service takes, where its command has them
    prefix = "slamlens"

    [service.estimator]           # the table's name is the service's name in the log
    command = "estimator"         # a slamlens command
    after = ["router"]            # start once these are ready
    robot = "${robot}"            # any other key: a setting of the command (its TOML key,
    checkpoint = "state"          #   as in docs/cli.md), a bus flag, config, verbose …

Per service the launch keys are ``command``, ``after``, ``ready`` (text of the stdout line
that says it is ready; default: the command's own "… ready" line, which every service
prints; "" = ready once started), ``respawn``, ``required`` (its exit ends the whole group
as a failure) and ``args`` (extra arguments, verbatim). Every other key must be a setting of
the command; its value is checked (type, choices, bounds) and turned into the flag the
command takes, then the whole command line is parsed by the command's own parser and its
settings built, ``--config`` file included — so a typo is one line naming the launch file,
the service and the key, before any process starts. A string value starting with ``~/`` is
the home folder's (a launch file is not read by a shell).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import shlex
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slamlens.common.cli import BusFlags, LogFlags, bus_settings
from slamlens.common.config import (
    check_value,
    flag_names,
    read_toml,
    setting,
    settings_from_args,
    settings_from_mapping,
    spec_of,
)
from slamlens.common.errors import ConfigError, SlamlensError
from slamlens.services.commands.cli import command_parser
from slamlens.services.commands.registry import COMMANDS

#: the line each command prints on stdout when it is ready to serve
READY_LINES = {"router": "router ready", "estimator": "estimator ready",
               "monitor": "monitor ready", "registration": "registration ready",
               "viewer": "viewer ready", "serial": "serial ready", "sim": "sim ready",
               "replay": "replay ready", "summary": "summary ready"}
#: commands that are not services (they do not run under a launch)
NOT_SERVICES = ("launch", "demo", "certs", "calibrate", "figures")
_LAUNCH_KEYS = ("command", "after", "ready", "respawn", "required", "args")
_TOP_KEYS = ("launch", "vars", "defaults", "service")
_VAR = re.compile(r"\$\{([^}]*)\}")
_NAME = re.compile(r"^[A-Za-z0-9_-]+$")


@dataclass(frozen=True)
class LaunchOptions:
    """The ``[launch]`` table: how the group is supervised."""

    description: str = setting("", doc="one line saying what the group is")
    respawn: bool = setting(True, doc="restart a service that exits with an error, with "
                                      "back-off (a service may say otherwise)")
    respawn_max_s: float = setting(10.0, doc="longest wait before a restart (the wait doubles "
                                             "from 0.5 s with each failure in a row)",
                                   unit="s", min=0.1)
    log_dir: str = setting("", doc="also write each service's output to DIR/NAME.log and the "
                                   "combined log to DIR/launch.log; empty = none",
                           metavar="DIR")


@dataclass(frozen=True)
class ServiceSpec:
    """One service of a launch, checked: how to start it and when."""

    name: str  #: its name in the log (the table's name)
    command: str  #: the slamlens command
    argv: tuple[str, ...]  #: the arguments after the command
    after: tuple[str, ...] = ()  #: services that must be ready before it starts
    ready: str = ""  #: text of the stdout line that says it is ready; "" = once started
    respawn: bool = True  #: restarted (with back-off) when it exits with an error
    required: bool = False  #: its exit for good ends the group as a failure

    def command_line(self) -> list[str]:
        return ["slamlens", self.command, *self.argv]

    def shell(self) -> str:
        return shlex.join(self.command_line())


@dataclass(frozen=True)
class LaunchPlan:
    """A whole launch: its options and its services in start order."""

    source: str  #: the file (or "slamlens demo") it came from, for messages
    options: LaunchOptions
    services: tuple[ServiceSpec, ...]

    def service(self, name: str) -> ServiceSpec:
        return next(s for s in self.services if s.name == name)


def load_launch(path: str | Path, *, values: Sequence[str] = ()) -> LaunchPlan:
    """Read and check a launch file; ``values`` are ``NAME=VALUE`` over its ``[vars]``."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"launch file {p} does not exist")
    return plan_from_mapping(read_toml(p, what="launch file"), source=str(p), values=values)


def _settings_class(command: str) -> type | None:
    return COMMANDS[command].settings_class()


def _known_fields(command: str) -> dict[str, tuple[type, dataclasses.Field]]:
    """Every key a service of ``command`` may set: its settings, the bus and log flags."""
    known: dict[str, tuple[type, dataclasses.Field]] = {}
    classes: list[type] = [LogFlags]
    if COMMANDS[command].bus:
        classes.insert(0, BusFlags)
    cls = _settings_class(command)
    if cls is not None:
        classes.insert(0, cls)
    for c in classes:
        for f in dataclasses.fields(c):
            if flag_names(f):
                known.setdefault(f.name, (c, f))
    return known


def _substitute(value: Any, variables: Mapping[str, str], where: str) -> Any:
    if isinstance(value, str):
        def one(match: re.Match[str]) -> str:
            name = match.group(1)
            if name not in variables:
                raise ConfigError(f"{where}: ${{{name}}} is not defined (add {name} to [vars] "
                                  f"or give --set {name}=VALUE)")
            return variables[name]

        text = _VAR.sub(one, value)
        return os.path.expanduser(text) if text.startswith("~/") or text == "~" else text
    if isinstance(value, list):
        return [_substitute(v, variables, where) for v in value]
    return value


def _flag_args(cls: type, f: dataclasses.Field, value: Any) -> tuple[list[str], list[str]]:
    """(flags, positionals) giving setting ``f`` the checked ``value``."""
    spec = spec_of(f)
    hint = typing.get_type_hints(cls)[f.name]
    name = flag_names(f)[-1]
    if spec.positional:
        items = value if isinstance(value, tuple) else (value,)
        return [], [str(v) for v in items]
    if spec.action == "count":
        return [name] * int(value), []
    if spec.action == "append":
        return [x for v in value for x in (name, str(v))], []
    if hint is bool:
        # a switch sets the non-default; the default is what the command has anyway
        return ([name] if bool(value) != bool(f.default) else []), []
    if isinstance(value, tuple):
        return [name, ",".join(str(v) for v in value)], []
    if value is None:
        return [], []
    return [name, repr(value) if isinstance(value, float) else str(value)], []


def _checked_argv(command: str, table: Mapping[str, Any], where: str) -> list[str]:
    """The arguments of ``slamlens COMMAND`` for a service table's settings."""
    known = _known_fields(command)
    flags: list[str] = []
    positionals: list[str] = []
    config = COMMANDS[command].config and _settings_class(command) is not None
    for key, value in table.items():
        if key == "config" and config:
            if not isinstance(value, str):
                raise ConfigError(f"{where} key 'config': expected a file name, got {value!r}")
            flags += ["--config", value]
            continue
        if key not in known:
            names = sorted([*known, *(("config",) if config else ())])
            raise ConfigError(f"{where}: unknown key {key!r}: neither a launch key "
                              f"({', '.join(_LAUNCH_KEYS)}) nor a setting of `slamlens "
                              f"{command}` ({', '.join(names)}; docs/cli.md)")
        cls, f = known[key]
        if isinstance(value, list):
            value = tuple(value)
        try:
            checked = check_value(cls, key, value)
        except ConfigError as exc:
            raise ConfigError(f"{where} key {key!r}: {exc}") from None
        more, pos = _flag_args(cls, f, checked)
        flags += more
        positionals += pos
    return [*positionals, *flags]


def _parse_whole(command: str, argv: list[str], where: str) -> None:
    """Parse ``argv`` with the command's own parser and build its settings (and, for a bus
    command, its Zenoh configuration): what the service itself will check at start."""
    parser = command_parser(command)

    def error(message: str) -> typing.NoReturn:  # argparse's complaint, not its exit
        raise ConfigError(f"{where}: {message}")

    parser.error = error  # type: ignore[method-assign]
    args = parser.parse_args(argv)
    cls = _settings_class(command)
    try:
        if cls is not None:
            settings_from_args(cls, args)
        if COMMANDS[command].bus:
            _check_bus(command, args)
    except SlamlensError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _check_bus(command: str, args: argparse.Namespace) -> None:
    from slamlens.common.session import build_config, router_settings

    bus = bus_settings(args)
    if command == "router":
        bus = router_settings(bus.listen, bus.zenoh_config, connect=bus.connect,
                              secure=bus.secure, name=bus.name, prefix=bus.prefix)
    build_config(bus)  # endpoints, the Zenoh file, the identity's certificate files


def _start_order(services: list[ServiceSpec], source: str) -> tuple[ServiceSpec, ...]:
    """The services in an order where each comes after what it waits for (file order
    otherwise); a cycle is an error naming it."""
    names = [s.name for s in services]
    for s in services:
        for other in s.after:
            if other not in names:
                raise ConfigError(f"{source} [service.{s.name}] key 'after': no service "
                                  f"{other!r} in the file (services: {', '.join(names)})")
            if other == s.name:
                raise ConfigError(f"{source} [service.{s.name}] key 'after': a service "
                                  "cannot wait for itself")
    done: list[ServiceSpec] = []
    left = list(services)
    while left:
        ready = [s for s in left if all(a in {d.name for d in done} for a in s.after)]
        if not ready:
            cycle = ", ".join(s.name for s in left)
            raise ConfigError(f"{source}: the services {cycle} wait for each other "
                              "(key 'after' makes a cycle)")
        done.append(ready[0])
        left.remove(ready[0])
    return tuple(done)


def plan_from_mapping(raw: Mapping[str, Any], *, source: str,
                      values: Sequence[str] = ()) -> LaunchPlan:
    """Check a parsed launch file (see the module docstring) into a :class:`LaunchPlan`."""
    unknown = sorted(set(raw) - set(_TOP_KEYS))
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {', '.join(unknown)}; a launch file has "
                          f"{', '.join(_TOP_KEYS)}")
    for key in _TOP_KEYS:
        if key in raw and not isinstance(raw[key], Mapping):
            raise ConfigError(f"{source}: key {key!r} must be a table [{key}]")
    try:
        options = settings_from_mapping(LaunchOptions, raw.get("launch", {}),
                                        source=f"{source} [launch]")
    except ConfigError as exc:
        raise ConfigError(f"{source} [launch]: {exc}") from None
    variables = _variables(raw.get("vars", {}), values, source)
    tables = raw.get("service", {})
    if not tables:
        raise ConfigError(f"{source}: no [service.NAME] table: nothing to launch")
    defaults = {k: _substitute(v, variables, f"{source} [defaults] key {k!r}")
                for k, v in raw.get("defaults", {}).items()}
    used_defaults: set[str] = set()
    specs = [_service(name, table, source=source, variables=variables, defaults=defaults,
                      options=options, used=used_defaults)
             for name, table in tables.items()]
    unused = sorted(set(defaults) - used_defaults)
    if unused:
        raise ConfigError(f"{source} [defaults]: key(s) {', '.join(unused)} are settings of "
                          "none of its services")
    return LaunchPlan(source=source, options=options, services=_start_order(specs, source))


def _variables(table: Mapping[str, Any], values: Sequence[str], source: str) -> dict[str, str]:
    """The file's [vars], with ``--set NAME=VALUE`` over them (only names the file has)."""
    variables: dict[str, str] = {}
    for name, value in table.items():
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise ConfigError(f"{source} [vars] key {name!r}: expected a string or a number, "
                              f"got {value!r}")
        variables[name] = str(value)
    for item in values:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ConfigError(f"--set {item!r}: expected NAME=VALUE")
        if name not in variables:
            raise ConfigError(f"--set {name}: {source} has no variable {name!r} in [vars] "
                              f"(it has: {', '.join(variables) or 'none'})")
        variables[name] = value
    return variables


def _service(name: str, table: Any, *, source: str, variables: Mapping[str, str],
             defaults: Mapping[str, Any], options: LaunchOptions,
             used: set[str]) -> ServiceSpec:
    """One [service.NAME] table, checked (the [defaults] it takes are added to ``used``)."""
    where = f"{source} [service.{name}]"
    if not _NAME.match(name) or name == "launch":
        raise ConfigError(f"{where}: a service name is letters, digits, '-' and '_', "
                          "and not 'launch' (the supervisor's own name in the log)")
    if not isinstance(table, Mapping):
        raise ConfigError(f"{source} key 'service.{name}' must be a table")
    command = table.get("command")
    if not isinstance(command, str) or command not in COMMANDS:
        choices = [c for c in COMMANDS if c not in NOT_SERVICES]
        raise ConfigError(f"{where} key 'command': {command!r} is not a slamlens "
                          f"service (one of {', '.join(choices)})")
    if command in NOT_SERVICES:
        raise ConfigError(f"{where} key 'command': `slamlens {command}` is not a service "
                          "a launch can run")
    own = {k: _substitute(v, variables, f"{where} key {k!r}") for k, v in table.items()}
    known = _known_fields(command)
    settings = {k: v for k, v in defaults.items() if k in known or k == "config"}
    used |= set(settings)
    settings.update({k: v for k, v in own.items() if k not in _LAUNCH_KEYS})
    argv = _checked_argv(command, settings, where)
    extra = own.get("args", [])
    if not isinstance(extra, list) or not all(isinstance(a, str) for a in extra):
        raise ConfigError(f"{where} key 'args': expected a list of strings")
    argv += extra
    _parse_whole(command, argv, where)
    after = own.get("after", [])
    if isinstance(after, str):
        after = [after]
    if not isinstance(after, list) or not all(isinstance(a, str) for a in after):
        raise ConfigError(f"{where} key 'after': expected a list of service names")
    ready = own.get("ready", READY_LINES.get(command, ""))
    respawn = own.get("respawn", options.respawn)
    required = own.get("required", False)
    for key, value in (("ready", ready), ("respawn", respawn), ("required", required)):
        expected = str if key == "ready" else bool
        if not isinstance(value, expected):
            raise ConfigError(f"{where} key {key!r}: expected "
                              f"{'a string' if expected is str else 'true or false'}, "
                              f"got {value!r}")
    return ServiceSpec(name=name, command=command, argv=tuple(argv), after=tuple(after),
                       ready=ready, respawn=respawn, required=required)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise ConfigError(f"cannot write {value!r} in a launch file")


def to_toml(raw: Mapping[str, Any]) -> str:
    """A launch file's tables (as :func:`plan_from_mapping` takes them) as TOML text."""
    lines: list[str] = []

    def table(header: str, values: Mapping[str, Any]) -> None:
        lines.append(f"[{header}]")
        lines.extend(f"{k} = {_toml_value(v)}" for k, v in values.items())
        lines.append("")

    for key in ("launch", "vars", "defaults"):
        if raw.get(key):
            table(key, raw[key])
    for name, values in raw.get("service", {}).items():
        table(f"service.{name}", values)
    return "\n".join(lines)
