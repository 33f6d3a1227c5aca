"""TOML configs for frozen dataclasses: load with overrides, check, write back.

Generic over any frozen dataclass whose fields are annotated with ``bool``, ``int``, ``float``,
``str``, ``Literal[...]``, ``tuple[T, ...]``, ``tuple[A, B]``, ``T | None`` or another such
dataclass (a TOML table). Layers merge in order (e.g. profile file, user file, ``--set``
overrides); :func:`load` then checks every key and type before calling the dataclass, whose own
``__post_init__`` checks ranges. Every error is a :class:`ConfigError` naming the dotted key, the
value and what is allowed; a mistyped key suggests the closest valid one.

    cfg = load(StudyConfig, merge(read_toml("paper.toml"), parse_sets(["base.noise_std=5"])))
    text = dump(cfg)          # fully resolved; load(StudyConfig, tomllib.loads(text)) == cfg
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import os
import stat
import tomllib
import types
import typing
import unicodedata
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import tomli_w

from workbench.validation import UserError

__all__ = ["MAX_CONFIG_BYTES", "MAX_NESTING", "ConfigError", "dump", "keys", "load", "merge",
           "parse_sets", "read_toml", "to_dict"]


class ConfigError(UserError):
    """A config key, type or value that is not allowed (the message says which and why)."""


MAX_CONFIG_BYTES = 1 << 20  # a config file is a few kB; anything above 1 MiB is not one
MAX_NESTING = 32  # tables and arrays inside one another (a config nests a few levels at most)
_KINDS = ((stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def read_toml(path: Path | str) -> dict[str, Any]:
    """A TOML file as a dict; every problem is a :class:`ConfigError` naming the path: it does
    not exist, is a folder, is not a regular file (a FIFO, a device such as /dev/zero, a
    socket: refused before opening, so reading never blocks), is larger than
    :data:`MAX_CONFIG_BYTES`, is not UTF-8 text (the first bad byte and its offset), holds a
    NUL byte (a binary file), or is not valid TOML (the line and column). A UTF-8 byte-order
    mark at the start is skipped. Tables and arrays nested more than :data:`MAX_NESTING`
    levels deep are refused."""
    path = Path(path)
    data = _read_capped(path)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config file {path} is not UTF-8 text (byte 0x{data[exc.start]:02x} "
                          f"at offset {exc.start}); save it as UTF-8 TOML") from None
    text = text.removeprefix("\ufeff")
    nul = text.find("\x00")
    if nul >= 0:
        raise ConfigError(f"config file {path} is not text: it holds a NUL byte at offset "
                          f"{data.find(0)} (a binary file?); give a TOML file")
    try:
        parsed = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from exc
    except RecursionError:
        raise ConfigError(f"{path}: not valid TOML (arrays or inline tables nest too "
                          f"deeply: a config nests at most {MAX_NESTING} levels)") from None
    _check_nesting(parsed, str(path))
    return parsed


def _depth(value: Any) -> int:
    """How many tables and arrays ``value`` holds inside one another (0 for a scalar)."""
    deepest, stack = 0, [(value, 0)]
    while stack:  # iterative: a deeply nested value cannot exhaust the call stack here
        node, level = stack.pop()
        if isinstance(node, Mapping):
            node = list(node.values())
        if isinstance(node, list | tuple):
            deepest = max(deepest, level + 1)
            if level < MAX_NESTING:  # deeper than the limit: the answer is known already
                stack.extend((v, level + 1) for v in node)
    return deepest


def _check_nesting(data: Any, where: str) -> None:
    if _depth(data) > MAX_NESTING:
        raise ConfigError(f"{where}: tables and arrays nest more than {MAX_NESTING} levels "
                          f"deep; a config nests at most {MAX_NESTING} levels")


def _read_capped(path: Path) -> bytes:
    """The bytes of the regular file ``path`` (at most :data:`MAX_CONFIG_BYTES`), checked with
    stat before opening and with fstat after (opened non-blocking, so a FIFO swapped in
    between cannot block either)."""
    limit = MAX_CONFIG_BYTES
    try:
        st = os.stat(path)
        _check_kind(path, st, limit)
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except ConfigError:
        raise
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist") from None
    except NotADirectoryError:
        raise ConfigError(f"config file {path} does not exist (a parent of it is a file, not "
                          "a folder)") from None
    except OSError as exc:
        raise ConfigError(f"config file {path} cannot be read ({exc.strerror or exc})"
                          ) from None
    try:
        _check_kind(path, os.fstat(fd), limit)
        chunks, size = [], 0
        while size <= limit:
            chunk = os.read(fd, limit + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except ConfigError:
        raise
    except OSError as exc:
        raise ConfigError(f"config file {path} cannot be read ({exc.strerror or exc})"
                          ) from None
    finally:
        os.close(fd)
    if size > limit:
        raise ConfigError(f"config file {path} is larger than {_size(limit)} (it grew while "
                          "being read); a config file is a small TOML file")
    return b"".join(chunks)


def _size(n: int) -> str:
    return f"{n / (1 << 20):g} MB" if n >= 1 << 20 else f"{n} bytes"


def _check_kind(path: Path, st: os.stat_result, limit: int) -> None:
    mode = st.st_mode
    if stat.S_ISDIR(mode):
        raise ConfigError(f"config file {path} is a folder, not a file; give the path of a "
                          "TOML file")
    if not stat.S_ISREG(mode):
        kind = next((name for test, name in _KINDS if test(mode)), "not a file")
        raise ConfigError(f"config file {path} is not a regular file: it is {kind}; give a "
                          "TOML file (write a generated config to a file first)")
    if st.st_size > limit:
        raise ConfigError(f"config file {path} is larger than {_size(limit)} ({st.st_size} "
                          "bytes); a config file is a small TOML file")


def parse_sets(items: Iterable[str], aliases: Mapping[str, str] | None = None) -> dict:
    """``["a.b=1", "c=[1, 2]", "d=before"]`` -> nested dict. Each item is exactly one
    ``key=value`` on one line: a control character (newline, carriage return, tab, ...) is an
    error, so that ``$'a=1\nb=2'`` is not read as a=1 with b=2 dropped. Values are TOML
    literals; a value that is not one (a bare word) is taken as a string. ``aliases`` maps
    short keys to dotted paths (e.g. ``noise_std`` -> ``base.noise_std``). A key of more than
    :data:`MAX_NESTING` dotted parts, or a value nested deeper, is an error."""
    out: dict[str, Any] = {}
    for item in items:
        if not isinstance(item, str):
            raise ConfigError(f"--set {item!r}: expected a string key=value")
        _one_line(item)
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected key=value (dotted keys for nested "
                              "fields, values as TOML literals, e.g. base.noise_std=5)")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        except RecursionError:
            raise _too_deep(item) from None
        key = (aliases or {}).get(key, key)
        *parents, last = key.split(".")
        if len(parents) + 1 > MAX_NESTING or len(parents) + _depth(value) > MAX_NESTING:
            raise _too_deep(item)
        node = out
        for p in parents:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {p} is set twice, as a value and a table")
        node[last] = value
    return out


def _too_deep(item: str) -> ConfigError:
    shown = item if len(item) <= 60 else item[:57] + "..."
    return ConfigError(f"--set {shown!r} ({len(item)} characters) nests more than {MAX_NESTING} "
                       "levels deep (dotted key parts, tables and arrays together); a config "
                       f"nests at most {MAX_NESTING} levels")


def _one_line(item: str) -> None:
    for i, ch in enumerate(item):
        if unicodedata.category(ch) == "Cc":  # C0 and C1 controls, DEL
            name = {"\n": "a newline", "\r": "a carriage return", "\t": "a tab"}.get(
                ch, "a control character")
            raise ConfigError(
                f"--set {item!r} is invalid: it contains {name} (U+{ord(ch):04X}) at position "
                f"{i}; each --set is exactly one key=value on one line, without control "
                "characters (repeat --set for more keys: --set a=1 --set b=2; inside a TOML "
                "string write \\n, \\t)")


def merge(*layers: Mapping[str, Any]) -> dict[str, Any]:
    """Later layers override earlier ones key by key; tables merge recursively."""
    out: dict[str, Any] = {}
    for layer in layers:
        for k, v in layer.items():
            if isinstance(v, Mapping) and isinstance(out.get(k), dict):
                out[k] = merge(out[k], v)
            else:
                out[k] = dict(v) if isinstance(v, Mapping) else v
    return out


def keys(cls: type, prefix: str = "") -> list[str]:
    """Every dotted key of a config dataclass (leaves only)."""
    out = []
    for f, hint in _fields(cls):
        inner = _dataclass_of(hint)
        out += keys(inner, f"{prefix}{f.name}.") if inner else [prefix + f.name]
    return out


def load(cls: type, data: Mapping[str, Any], *, path: str = "",
         aliases: Mapping[str, str] | None = None) -> Any:
    """An instance of the dataclass ``cls`` from ``data`` (missing keys take the defaults).
    A nested table that sets only some keys keeps the others from the field's own default
    (``sampler = MPPIConfig(sigma=5)`` with ``sampler.n_samples = 256`` keeps sigma 5), not
    from the nested class's defaults. ``aliases`` (short key -> dotted key) are offered as
    suggestions for mistyped keys."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path or 'config'} = {data!r} is invalid: expected a table")
    fields = dict(_fields(cls))
    names = {f.name: f for f in fields}
    for k in data:
        if k not in names:
            raise ConfigError(_unknown(cls, path, k, aliases or {}))
    kwargs = {}
    for f, hint in fields.items():
        if f.name in data:
            value, sub = data[f.name], _dataclass_of(hint)
            default = f.default_factory() if f.default_factory is not dataclasses.MISSING \
                else f.default
            if sub is not None and isinstance(value, Mapping) and isinstance(default, sub):
                value = merge(to_dict(default), value)
            kwargs[f.name] = _convert(hint, value, path + f.name)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        where = f"{path[:-1]}: " if path else ""
        raise ConfigError(f"{where}{exc}") from exc


def to_dict(obj: Any) -> dict[str, Any]:
    """A config dataclass as TOML-ready data: tuples as lists, tables for nested dataclasses,
    enums by value; fields that are None are left out (TOML has no null)."""
    out = {}
    for f in dataclasses.fields(obj):
        if not f.init:  # computed in __post_init__, not a setting
            continue
        v = _plain(getattr(obj, f.name))
        if v is not None:
            out[f.name] = v
        elif f.default is not None:  # leaving it out would load the default instead
            raise ConfigError(f"{f.name} = None cannot be written to TOML (its default is "
                              f"{f.default!r})")
    return out


def dump(obj: Any, header: str = "") -> str:
    """The fully resolved config as TOML text (comment lines from ``header`` first)."""
    text = tomli_w.dumps(to_dict(obj))
    lines = [f"# {line}".rstrip() for line in header.splitlines()] if header else []
    return "\n".join([*lines, text]) if lines else text


# ---------------------------------------------------------------------------------- internals
def _fields(cls: type) -> list[tuple[dataclasses.Field, Any]]:
    hints = typing.get_type_hints(cls)
    return [(f, hints[f.name]) for f in dataclasses.fields(cls) if f.init]


def _dataclass_of(hint) -> type | None:
    return hint if isinstance(hint, type) and dataclasses.is_dataclass(hint) else None


def _unknown(cls: type, path: str, key: str, aliases: Mapping[str, str]) -> str:
    valid = [path + k for k in keys(cls)]
    full = path + key
    # candidates: dotted keys, their last part, and the aliases (short names users type)
    names = {**{k: k for k in valid}, **{k.rsplit(".", 1)[-1]: k for k in valid},
             **{a: target for a, target in aliases.items() if target in valid}}
    close = difflib.get_close_matches(full, list(names), n=1, cutoff=0.6) or \
        difflib.get_close_matches(key, list(names), n=1, cutoff=0.6)
    hint = ""
    if close:
        short, target = close[0], names[close[0]]
        hint = f"; did you mean {short!r}" + (f" ({target})" if target != short else "") + "?"
    return f"unknown key {full!r}{hint} (valid keys: {', '.join(valid)})"


def _describe(hint) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_describe(args[0])}"
        return f"a list of {len(args)} items ({', '.join(_describe(a) for a in args)})"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in args if a is not type(None))
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        return "one of " + ", ".join(repr(m.value) for m in hint)
    if _dataclass_of(hint):
        return f"a table ({hint.__name__})"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(
        hint, getattr(hint, "__name__", str(hint)))


def _bad(key: str, value, hint) -> ConfigError:
    return ConfigError(f"{key} = {value!r} is invalid: expected {_describe(hint)}")


def _convert(hint, value, key: str):
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if _dataclass_of(hint):
        if isinstance(value, Mapping):
            return load(hint, value, path=key + ".")
        raise _bad(key, value, hint)
    if origin in (typing.Union, types.UnionType):
        for a in args:
            if a is type(None):
                continue
            try:
                return _convert(a, value, key)
            except ConfigError:
                pass
        raise _bad(key, value, hint)
    if origin is typing.Literal:
        if value in args and type(value) in {type(a) for a in args}:
            return value
        raise _bad(key, value, hint)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise _bad(key, value, hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise _bad(key, value, hint)
        return tuple(_convert(a, v, f"{key}[{i}]") for i, (a, v) in
                     enumerate(zip(args, value, strict=True)))
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        try:
            return hint(value)
        except ValueError:
            raise _bad(key, value, hint) from None
    if hint is bool:
        if isinstance(value, bool):
            return value
    elif hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif hint is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
    elif hint is str:
        if isinstance(value, str):
            return value
    elif hint is Any:
        return value
    else:
        raise ConfigError(f"{key}: fields of type {hint!r} cannot be read from TOML")
    raise _bad(key, value, hint)


def _plain(v):
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return to_dict(v)
    if isinstance(v, enum.Enum):
        return v.value
    if isinstance(v, tuple | list):
        return [_plain(x) for x in v]
    if isinstance(v, Mapping):
        return {str(k): _plain(x) for k, x in v.items()}
    if hasattr(v, "item") and callable(v.item):  # numpy scalars
        return v.item()
    return v
