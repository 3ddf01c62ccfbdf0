"""Typed ``case.toml`` tables: how one TOML table becomes one frozen dataclass, checked in one place.

A table class is a frozen dataclass whose fields are the table's keys. The annotation says what
a value must be (``float``, ``int``, ``bool``, ``str``, ``tuple[float, ...]``, unions of these,
``| None``); a field made with :func:`positive`, :func:`non_negative`, :func:`fraction`,
:func:`port` or :func:`one_of` also carries its range. A field whose type is itself a table class
is *flattened*: its keys sit in the same TOML table (``[registration]`` holds the pairing keys).
A class may add checks across keys in ``validate(self)``, raising :class:`SettingError`.

:func:`parse_table` refuses an unknown key (a typo), a value of the wrong type (a boolean or a
string is not a number, ``3.5`` is not a count) and a value out of range, with one line naming
the file, the table and the key. Adding a key to a table is one line: a field with its default.
"""

from __future__ import annotations

import math
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import MISSING, Field, field, fields, is_dataclass, replace
from typing import Any, TypeVar

from .errors import EMRegError

T = TypeVar("T")


class SettingError(ValueError):
    """A bad value in a table; ``key`` names it (None for a check across keys)."""

    def __init__(self, message: str, key: str | None = None) -> None:
        super().__init__(message)
        self.key = key


# --- fields with a range -----------------------------------------------------------------------

_RANGES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "positive": (lambda v: v > 0, "must be a positive number"),
    "non_negative": (lambda v: v >= 0, "must not be negative"),
    "fraction": (lambda v: 0 < v <= 1, "must lie in (0, 1]"),
    "port": (lambda v: 1 <= v <= 255, "must be a port number (1 or more: 1..4 on a trakSTAR)"),
}


def positive(default: Any) -> Any:
    """A field whose value must be > 0 (None passes when the type allows it)."""
    return field(default=default, metadata={"range": "positive"})


def non_negative(default: Any) -> Any:
    """A field whose value must be >= 0."""
    return field(default=default, metadata={"range": "non_negative"})


def fraction(default: Any) -> Any:
    """A field whose value must lie in (0, 1]."""
    return field(default=default, metadata={"range": "fraction"})


def port(default: int) -> Any:
    """A tracker port number (1..4 on a trakSTAR, more on an Aurora; whether the recording holds it is
    checked where the recording is read)."""
    return field(default=default, metadata={"range": "port"})


def one_of(default: Any, *choices: Any) -> Any:
    """A field whose value must be one of ``choices``."""
    return field(default=default, metadata={"choices": tuple(choices)})


# --- parsing -----------------------------------------------------------------------------------


def table_keys(cls: type) -> list[str]:
    """Every key a table class accepts (the fields of flattened sub-tables included)."""
    hints = typing.get_type_hints(cls)
    keys: list[str] = []
    for f in fields(cls):
        if _is_table(hints[f.name]):
            keys.extend(table_keys(hints[f.name]))
        else:
            keys.append(f.name)
    return keys


def parse_table(cls: type[T], values: Any, table: str, source: str = "case.toml", base: T | None = None,
                ignore_unknown: bool = False) -> T:
    """An instance of the table class ``cls`` from a TOML table (a mapping; None = empty).

    Keys absent from ``values`` keep the value of ``base`` (default: the class defaults).
    Raises :class:`EMRegError` with one line ``SOURCE: [TABLE] KEY what is wrong`` for an unknown
    key (unless ``ignore_unknown``), a value of the wrong type or out of range.
    """
    if values is None:
        values = {}
    if not isinstance(values, Mapping):
        raise EMRegError(f"{source}: {table} must be a table ([{table}] with keys), got {values!r:.60}")
    known = table_keys(cls)
    unknown = sorted(set(values) - set(known))
    if unknown and not ignore_unknown:
        raise EMRegError(f"{source}: [{table}] unknown key{'s' if len(unknown) > 1 else ''} "
                         f"{', '.join(unknown)}; known: {', '.join(sorted(known))}")
    try:
        return _build(cls, values, base)
    except SettingError as exc:
        where = f" {exc.key}" if exc.key else ""
        raise EMRegError(f"{source}: [{table}]{where} {exc}") from None
    except EMRegError as exc:  # a class's own __post_init__ check
        raise EMRegError(f"{source}: [{table}] {exc}") from None


def _build(cls: type[T], values: Mapping[str, Any], base: T | None) -> T:
    hints = typing.get_type_hints(cls)
    converted: dict[str, Any] = {}
    for f in fields(cls):
        hint = hints[f.name]
        if _is_table(hint):
            sub_keys = set(table_keys(hint))
            sub_values = {k: v for k, v in values.items() if k in sub_keys}
            if sub_values or base is None:
                converted[f.name] = _build(hint, sub_values, None if base is None else getattr(base, f.name))
        elif f.name in values:
            converted[f.name] = _check_range(f, _convert(values[f.name], hint, f.name))
    instance = replace(base, **converted) if base is not None else cls(**converted)
    validate = getattr(instance, "validate", None)
    if validate is not None:
        validate()
    return instance


def _is_table(hint: Any) -> bool:
    return isinstance(hint, type) and is_dataclass(hint)


def _check_range(f: Field, value: Any) -> Any:
    if value is None:
        return value
    choices = f.metadata.get("choices")
    if choices is not None and value not in choices:
        raise SettingError(f"must be one of {', '.join(repr(c) for c in choices)}, got {value!r}", f.name)
    name = f.metadata.get("range")
    if name is not None:
        accept, message = _RANGES[name]
        if not accept(value):
            raise SettingError(f"{message}, got {value!r}", f.name)
    return value


def _convert(value: Any, hint: Any, key: str) -> Any:
    """``value`` as the annotation ``hint`` asks, or a :class:`SettingError`."""
    origin = typing.get_origin(hint)
    if origin in (types.UnionType, typing.Union):
        members = [m for m in typing.get_args(hint) if m is not type(None)]
        if value is None and len(members) < len(typing.get_args(hint)):
            return None
        for member in members:
            try:
                return _convert(value, member, key)
            except SettingError:
                continue
        raise SettingError(f"must be {' or '.join(_describe(m) for m in members)}, got {value!r:.60}", key)
    if origin is tuple:
        item = typing.get_args(hint)[0]
        if not isinstance(value, (list, tuple)):
            raise SettingError(f"must be {_describe(hint)}, got {value!r:.60}", key)
        return tuple(_convert(v, item, key) for v in value)
    return _convert_scalar(value, hint, key)


def _convert_scalar(value: Any, hint: Any, key: str) -> Any:
    if hint is bool:
        if not isinstance(value, bool):
            raise SettingError(f"must be true or false, got {value!r:.60}", key)
        return value
    if hint is str:
        if not isinstance(value, str):
            raise SettingError(f"must be a string, got {value!r:.60}", key)
        return value
    if hint in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SettingError(f"must be {_describe(hint)}, got {value!r:.60}", key)
        if not math.isfinite(value):
            raise SettingError(f"must be a finite number, got {value!r}", key)
        if hint is int:
            if value != int(value):
                raise SettingError(f"must be a whole number, got {value!r}", key)
            return int(value)
        return float(value)
    raise TypeError(f"table field {key}: unsupported type {hint!r}")  # a programming error, not the user's


def _describe(hint: Any) -> str:
    if typing.get_origin(hint) is tuple:
        item = _describe(typing.get_args(hint)[0]).removeprefix("a ")
        return f"a list of {item}s"
    return {bool: "true or false", str: "a string", int: "a whole number", float: "a number"}.get(hint, str(hint))


def defaults_of(cls: type) -> dict[str, Any]:
    """The default value of every key of a table class (flattened), for documentation and tests."""
    hints = typing.get_type_hints(cls)
    out: dict[str, Any] = {}
    for f in fields(cls):
        if _is_table(hints[f.name]):
            out.update(defaults_of(hints[f.name]))
        elif f.default is not MISSING:
            out[f.name] = f.default
    return out
