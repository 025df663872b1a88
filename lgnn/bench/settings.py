"""Typed settings from TOML: a nested dict checked against frozen dataclasses, and
command-line overrides of any value.

`build(cls, data)` makes a `cls` instance from a dict (a TOML table): each key must be
a field (an unknown one is a `ConfigError` naming its dotted path, e.g.
`training.train.epoch`), each value must have the field's type (`int`, `float` (an
integer is accepted), `bool`, `str`, tuples from TOML arrays, nested dataclasses from
tables, `None` from the string "none" where the field allows it); missing fields take
the dataclass's default (a nested dataclass without one: its own defaults). The
dataclass's own checks (`__post_init__`) then run as usual.

`apply_overrides(data, ["a.b=value", ...])` sets dotted keys in the dict before it is
built: `value` is read as a TOML value (`50`, `1e-3`, `true`, `[0, 1, 2]`,
`"chain4"`), and, for the shell's sake, an unquoted word or a bracketed list of words
(`chain4`, `[chain4,chain8]`) as strings.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from pathlib import Path

from lgnn.errors import ConfigError
from lgnn.files import check_regular_input

NONE = "none"


def read_toml(path: str | Path) -> dict:
    """The TOML file at `path` as a dict; `ConfigError` (one line) if unreadable."""
    check_regular_input(path, "config file")
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except OSError as err:
        raise ConfigError(f"cannot read config {path}: {err.strerror or err}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"config {path}: not a text (UTF-8) file") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"config {path}: not valid TOML ({err})") from None
    except RecursionError:
        raise ConfigError(f"config {path}: not valid TOML (nested too deeply)") from None


def build(cls, data: dict, where: str = ""):
    """A `cls` dataclass instance from `data` (module docstring)."""
    if not isinstance(data, dict):
        raise ConfigError(f"setting {where.rstrip('.') or cls.__name__!r} must be a table, got {_show(data)}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    for key in data:
        if key not in fields:
            raise ConfigError(f"unknown setting {where + key!r} (choose from {', '.join(fields)})")
    values = {}
    for name, field in fields.items():
        if name in data:
            values[name] = _convert(data[name], hints[name], where + name)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            if not dataclasses.is_dataclass(hints[name]):
                raise ConfigError(f"missing setting {where + name!r}")
            values[name] = build(hints[name], {}, f"{where}{name}.")
    return cls(**values)


def _show(value) -> str:
    return repr(value) if not isinstance(value, dict) else "a table"


def _convert(value, hint, where: str):
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if type(None) in args and value == NONE:
            return None
        others = [a for a in args if a is not type(None)]
        errors = []
        for option in others:
            try:
                return _convert(value, option, where)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError(errors[0] + (f" or {NONE!r}" if type(None) in args else ""))
    if dataclasses.is_dataclass(hint):
        return build(hint, value, where + ".")
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"setting {where!r} must be a list, got {_show(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{where}[{k}]") for k, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"setting {where!r} must be a list of {len(args)}, got {_show(value)}")
        return tuple(_convert(v, a, f"{where}[{k}]") for k, (v, a) in enumerate(zip(value, args)))
    if hint is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if hint in (int, bool, str) and type(value) is hint:
        return value
    raise ConfigError(f"setting {where!r} must be {getattr(hint, '__name__', hint)}, got {_show(value)}")


def parse_override(text: str) -> tuple[str, object]:
    """`"a.b=value"` as `("a.b", value)` (module docstring for how values are read)."""
    key, sep, raw = text.partition("=")
    key, raw = key.strip(), raw.strip()
    if not sep or not key:
        raise ConfigError(f"--set expects KEY=VALUE (e.g. training.train.epochs=50), got {text!r}")
    return key, _value(raw)


def _value(raw: str):
    try:
        return tomllib.loads(f"value = {raw}")["value"]
    except tomllib.TOMLDecodeError:
        pass
    except RecursionError:
        raise ConfigError(f"--set value nested too deeply: {raw[:20]}...") from None
    if raw.startswith("[") and raw.endswith("]"):
        return [_value(item.strip()) for item in raw[1:-1].split(",") if item.strip()]
    return raw


def apply_overrides(data: dict, overrides) -> dict:
    """A copy of `data` with every `KEY=VALUE` of `overrides` set (dotted keys reach
    into tables, creating them; which keys exist is checked by `build`)."""
    data = _copy(data)
    for text in overrides:
        key, value = parse_override(text)
        parts = key.split(".")
        table = data
        for k, part in enumerate(parts[:-1]):
            node = table.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {key}: setting {'.'.join(parts[: k + 1])!r} is not a table")
            table = node
        table[parts[-1]] = value
    return data


def merged(base: dict, data: dict) -> dict:
    """`base` with `data`'s values set over it, table by table (a config on top of a profile)."""
    out = _copy(base)
    for key, value in data.items():
        out[key] = merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else _copy(value)
    return out


def _copy(data):
    if isinstance(data, dict):
        return {k: _copy(v) for k, v in data.items()}
    if isinstance(data, list):
        return [_copy(v) for v in data]
    return data
