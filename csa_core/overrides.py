"""``--set section.name=value``: one override path for every dataclass config tree.

The adaptation config (``csa_core.adapt.config.AdaptConfig``) and the NeRF config
(``csa_core.nerf.config.NerfConfig``) are trees of dataclasses. :func:`apply_overrides` sets
any leaf field of such a tree from ``dotted.path=value`` text, the way ``csa adapt``,
``csa experiment ...``, ``csa demo``, ``csa nerf fit`` and the NeRF benchmarks read their
``--set`` flags (docs/presets.md "Overriding a preset").

Values are parsed by the field's declared type, never evaluated as code: ``bool``
(true/false, 1/0, on/off, yes/no), ``int``, ``float``, ``str``, ``Literal[...]`` (one of the
allowed values), ``X | None`` (``none`` or ``null`` for None), and tuples and lists written
as Python literals (``optim.betas=(0.9,0.99)``), their items checked against the item type.
A nested dataclass (a section) cannot be set whole, only its fields; an optional section
(``X | None``) can be set to ``none`` (off) or to ``default`` (on, with the defaults of its
class, e.g. ``seg.augment=default`` before ``seg.augment.rotation_deg=10``).

A section may also take keys that are not its fields, through a method
``override_key(key, text, where) -> bool`` that returns whether it took the key (the rest of
the dotted path below the section, and the value's text); its class attribute
``OVERRIDE_KEYS`` names them among the valid ones when a key is unknown. The adaptation
budget's NeRF section (``csa_core.adapt.config.NerfBudget``) takes ``config.<NerfConfig key>``
that way, and the keys of its earlier fields.
"""

from __future__ import annotations

import ast
import dataclasses
import types
import typing
from collections.abc import Iterable
from typing import Any, Literal, TypeVar, Union

from csa_core.errors import CSAInputError

T = TypeVar("T")

TRUE_WORDS = ("true", "1", "on", "yes")
FALSE_WORDS = ("false", "0", "off", "no")
NONE_WORDS = ("none", "null")
DEFAULT_WORD = "default"  # an optional section switched on with its class's defaults


class _BadValue(Exception):
    """A value that does not fit a type; the message says what was expected."""


def apply_overrides(config: T, items: Iterable[str], flag: str = "--set") -> T:
    """Set ``dotted.path=value`` items on the dataclass tree ``config``, in order.

    ``config`` is changed **in place** and returned. After the last item, every dataclass in
    the tree that has a ``__post_init__`` runs it again (innermost first), so a combination
    its validation rejects is rejected here too. Every error is a
    :class:`~csa_core.errors.CSAInputError` whose place is ``flag`` and the item, and which
    names the key and what is wrong: an unknown field (with the valid names at that level),
    a section set whole, or a value that does not parse as the field's type (with the type
    expected). On an error the config may be partly changed: build a fresh one to retry.
    """
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError(f"apply_overrides needs a dataclass instance, got {type(config).__name__}")
    items = list(items)
    for item in items:
        _apply_one(config, item, flag)
    if items:
        try:
            _revalidate(config)
        except (ValueError, TypeError) as err:
            where = " ".join(f"{flag} {item}" for item in items)
            raise CSAInputError(where, f"invalid config: {err}") from None
    return config


def _apply_one(config: Any, item: str, flag: str) -> None:
    where = f"{flag} {item}"
    key, sep, text = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise CSAInputError(where, "expected KEY=VALUE, e.g. collapse.enabled=false")
    parts = key.split(".")
    obj = config
    for depth, name in enumerate(parts):
        here = ".".join(parts[:depth])
        names = [f.name for f in dataclasses.fields(obj)]
        if name not in names:
            taker = getattr(obj, "override_key", None)
            if callable(taker) and taker(".".join(parts[depth:]), text.strip(), where):
                return
            level = f"section {here!r}" if here else type(obj).__name__
            valid = [*names, *getattr(obj, "OVERRIDE_KEYS", ())]
            raise CSAInputError(
                where,
                f"unknown key {key!r}: {level} has no field {name!r} (valid: {', '.join(valid)})",
            )
        value = getattr(obj, name)
        if depth == len(parts) - 1:
            break
        if not dataclasses.is_dataclass(value):
            section = ".".join(parts[: depth + 1])
            if value is None and _is_optional_section(_field_types(type(obj), where)[name]):
                raise CSAInputError(
                    where,
                    f"{section!r} is none (off) in this config: it has no fields to set "
                    f"(switch it on first with {section}={DEFAULT_WORD})",
                )
            raise CSAInputError(
                where,
                f"unknown key {key!r}: {section!r} is a field, "
                "not a section with fields of its own",
            )
        obj = value
    tp = _field_types(type(obj), where)[name]
    text = text.strip()
    if _is_optional_section(tp) and text.lower() == DEFAULT_WORD:
        section_cls = next(a for a in typing.get_args(tp) if dataclasses.is_dataclass(a))
        _set(obj, name, section_cls(), key, where)
        return
    if dataclasses.is_dataclass(value):
        optional = type(None) in typing.get_args(tp)
        if optional and text.lower() in NONE_WORDS:
            _set(obj, name, None, key, where)
            return
        fields = ", ".join(f"{key}.{f.name}" for f in dataclasses.fields(value))
        whole = f" (only to none or {DEFAULT_WORD}: {key}=none)" if optional else ""
        raise CSAInputError(
            where, f"{key!r} is a section and cannot be set whole{whole}; set its fields: {fields}"
        )
    _set(obj, name, parse_value(text, tp, key, where), key, where)


def parse_value(text: str, tp: Any, key: str, where: str) -> Any:
    """``text`` read as a value of type ``tp``, as every ``--set`` item's value is (also for a
    section's ``override_key``, the module docstring); a bad value is a
    :class:`~csa_core.errors.CSAInputError` at ``where`` that names ``key``."""
    try:
        return _parse(text.strip(), tp)
    except _BadValue as err:
        raise CSAInputError(where, f"bad value for {key!r}: expected {err}") from None


def _set(obj: Any, name: str, value: Any, key: str, where: str) -> None:
    try:
        setattr(obj, name, value)
    except dataclasses.FrozenInstanceError:
        raise CSAInputError(
            where, f"{key!r} belongs to a frozen config and cannot be set"
        ) from None


def _is_optional_section(tp: Any) -> bool:
    """Whether ``tp`` is ``SomeDataclass | None``."""
    args = typing.get_args(tp)
    return type(None) in args and any(dataclasses.is_dataclass(a) for a in args)


def _field_types(cls: type, where: str) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except (NameError, TypeError) as err:  # annotations that do not resolve at run time
        raise CSAInputError(
            where, f"cannot read the field types of {cls.__name__}: {err}"
        ) from None


def _revalidate(obj: Any) -> None:
    """Run ``__post_init__`` of every dataclass in the tree under ``obj``, innermost first."""
    for f in dataclasses.fields(obj):
        child = getattr(obj, f.name)
        if dataclasses.is_dataclass(child) and not isinstance(child, type):
            _revalidate(child)
    post_init = getattr(obj, "__post_init__", None)
    if post_init is not None:
        post_init()


def _describe(tp: Any) -> str:
    """A type as the error messages name it."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is type(None):
        return "none"
    if origin is Literal:
        return "one of " + ", ".join(str(a) for a in args)
    if origin in (Union, types.UnionType):
        return " or ".join(_describe(a) for a in args)
    if origin in (tuple, list):
        fixed = origin is tuple and args and args[-1] is not Ellipsis
        items = [a for a in args if a is not Ellipsis][: None if fixed else 1]
        kinds = f" (items: {', '.join(_describe(a) for a in items)})" if items else ""
        return f"a {origin.__name__} literal like {_example(tp)}{kinds}"
    return {bool: "true or false", int: "an integer", float: "a number", str: "text"}.get(
        tp, getattr(tp, "__name__", str(tp))
    )


def _example(tp: Any) -> str:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is tuple and args and args[-1] is not Ellipsis:
        return "(" + ",".join("1" for _ in args) + ")"
    return "(1,2)" if origin is tuple else "[1,2]"


def _parse(text: str, tp: Any) -> Any:
    """``text`` as a value of type ``tp``; :class:`_BadValue` when it is not one."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (Union, types.UnionType):
        if type(None) in args and text.lower() in NONE_WORDS:
            return None
        for option in args:
            if option is type(None):
                continue
            try:
                return _parse(text, option)
            except _BadValue:
                continue
        raise _BadValue(f"{_describe(tp)}, got {text!r}")
    if tp is type(None):
        if text.lower() in NONE_WORDS:
            return None
        raise _BadValue(f"none, got {text!r}")
    if origin is Literal:
        for allowed in args:
            if isinstance(allowed, str):
                if text == allowed:
                    return allowed
            else:
                try:
                    if _parse(text, type(allowed)) == allowed:
                        return allowed
                except _BadValue:
                    continue
        raise _BadValue(f"{_describe(tp)}, got {text!r}")
    if origin in (tuple, list):
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
            raise _BadValue(f"{_describe(tp)}, got {text!r}") from None
        return _coerce(value, tp, text)
    if tp is str:
        return text
    if tp is bool:
        low = text.lower()
        if low in TRUE_WORDS:
            return True
        if low in FALSE_WORDS:
            return False
        raise _BadValue(f"true or false (also 1/0, on/off, yes/no), got {text!r}")
    if tp is int:
        try:
            return int(text)
        except ValueError:
            raise _BadValue(f"an integer, got {text!r}") from None
    if tp is float:
        try:
            return float(text)
        except ValueError:
            raise _BadValue(f"a number, got {text!r}") from None
    if tp is Any:
        raise _BadValue("a field of a declared type (this one is Any and cannot be set)")
    if dataclasses.is_dataclass(tp):
        raise _BadValue(f"none or the fields of a {tp.__name__} section, one by one")
    raise _BadValue(f"a type --set can parse ({_describe(tp)} is not one)")


def _coerce(value: Any, tp: Any, text: str) -> Any:
    """A Python literal ``value`` checked against ``tp`` (items of tuples and lists too)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    bad = _BadValue(f"{_describe(tp)}, got {text!r}")
    if origin in (Union, types.UnionType):
        for option in args:
            try:
                return _coerce(value, option, text)
            except _BadValue:
                continue
        raise bad
    if tp is type(None):
        if value is None:
            return None
        raise bad
    if origin is Literal:
        if any(value == a and type(value) is type(a) for a in args):
            return value
        raise bad
    if origin in (tuple, list):
        if not isinstance(value, (tuple, list)):
            raise bad
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise _BadValue(f"{len(args)} items like {_example(tp)}, got {text!r}")
            try:
                items = [_coerce(v, a, text) for v, a in zip(value, args, strict=True)]
            except _BadValue:
                raise bad from None
        else:
            item_tp = args[0] if args else Any
            try:
                items = [v if item_tp is Any else _coerce(v, item_tp, text) for v in value]
            except _BadValue:
                raise bad from None
        return tuple(items) if origin is tuple else items
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise bad
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise bad
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise bad
    if tp is str:
        if isinstance(value, str):
            return value
        raise bad
    if tp is Any:
        return value
    raise bad
