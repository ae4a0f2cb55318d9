"""Frozen-dataclass configs: plain-dict view, overrides from a dict or a TOML file, a stable hash, a readable diff.

Every stage takes a frozen dataclass (nested dataclasses allowed) with documented defaults. The workspace stores
`to_dict(config)` and `config_hash(config)` so that a rerun can tell whether its results may be mixed with the
ones already on disk. A field declared with `field(default=..., metadata={"hash": False})` (e.g. a worker count)
does not change results, so it is left out of the hash and of the stored dict.
"""

import dataclasses
import hashlib
import json
import math
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any, TypeVar

from .errors import InputError

ConfigT = TypeVar("ConfigT")  # a config dataclass


def _hashed_fields(cfg):
    return [f for f in dataclasses.fields(cfg) if f.metadata.get("hash", True)]


def to_dict(cfg: object, *, all_fields: bool = False) -> dict:
    """Nested plain dict of a config (tuples become lists); unhashed fields only with `all_fields`."""
    out = {}
    for f in (dataclasses.fields(cfg) if all_fields else _hashed_fields(cfg)):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            value = to_dict(value, all_fields=all_fields)
        elif isinstance(value, tuple):
            value = list(value)
        elif isinstance(value, Path):
            value = str(value)
        out[f.name] = value
    return out


def config_hash(cfg_or_dict: object) -> str:
    """SHA-256 (16 hex digits) of the canonical JSON of a config: equal configs give equal hashes across runs."""
    d = cfg_or_dict if isinstance(cfg_or_dict, dict) else to_dict(cfg_or_dict)
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


def bounded(default: object, low: float | None = None, high: float | None = None, *, low_open: bool = False,
            **metadata: object) -> Any:
    """A config field whose overrides (a TOML file or a flag) must lie in [low, high], or (low, high] with
    `low_open`: a negative image size or a ratio of 5 is refused when given, not met as a crash later."""
    return dataclasses.field(default=default,
                             metadata={"low": low, "high": high, "low_open": low_open, **metadata})


def _checked(f, current, value, where: str):
    """`value` for field `f` (whose default-derived value is `current`), of the field's type and within its
    bounds; an InputError naming `where` otherwise."""
    if isinstance(value, dict):
        raise InputError(f"{where}: expected a single value, not a table")
    if current is None or (isinstance(current, str) and isinstance(value, str)):
        return value
    if isinstance(current, (tuple, list)):
        if not isinstance(value, (tuple, list)):
            raise InputError(f"{where}: expected a list, got {value!r}")
        if not current:
            return tuple(value)
        if not value:
            raise InputError(f"{where}: expected a non-empty list")
        # every entry like the default's first one: its type, and the field's bounds
        return tuple(_checked(f, current[0], v, f"{where}[{k}]") for k, v in enumerate(value))
    if isinstance(current, bool) or isinstance(value, bool):
        if type(value) is not type(current):
            raise InputError(f"{where}: expected {type(current).__name__}, got {value!r}")
        return value
    if isinstance(current, float) and isinstance(value, (int, float)):
        value = float(value)
    elif type(value) is not type(current):
        expected = "a whole number" if isinstance(current, int) else type(current).__name__
        raise InputError(f"{where}: expected {expected}, got {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise InputError(f"{where}: expected a finite number, got {value!r}")
    low, high = f.metadata.get("low"), f.metadata.get("high")
    if low is not None and (value < low or f.metadata.get("low_open") and value == low):
        raise InputError(f"{where}: must be {'above' if f.metadata.get('low_open') else 'at least'} {low}, "
                         f"got {value!r}")
    if high is not None and value > high:
        raise InputError(f"{where}: must be at most {high}, got {value!r}")
    return value


def with_overrides(cfg: ConfigT, overrides: dict, *, source: str = "overrides") -> ConfigT:
    """A copy of `cfg` with fields replaced from a (nested) dict; unknown keys, values of the wrong type and
    values outside a `bounded` field's range raise InputError naming `source` and the key."""
    fields = {f.name: f for f in dataclasses.fields(cfg)}
    changes = {}
    for key, value in overrides.items():
        if key not in fields:
            raise InputError(f"{source}: unknown option {key!r} in {type(cfg).__name__} "
                             f"(known: {', '.join(sorted(fields))})")
        current = getattr(cfg, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise InputError(f"{source}: {key!r} must be a table of options")
            changes[key] = with_overrides(current, value, source=f"{source}: {key}")
        else:
            changes[key] = _checked(fields[key], current, value, f"{source}: {key}")
    return dataclasses.replace(cfg, **changes)


def with_field(cfg: ConfigT, path: tuple[str, ...], value: object, *, where: str) -> ConfigT:
    """A copy of `cfg` with the (nested) field at `path`, e.g. ("sift", "max_num_features"), set to `value`,
    checked as `with_overrides` checks it; an InputError names `where` (the flag the user gave, say) instead of
    the field, whose name the user may never have seen."""
    name, rest = path[0], path[1:]
    current = getattr(cfg, name)
    if rest:
        return dataclasses.replace(cfg, **{name: with_field(current, rest, value, where=where)})
    field = next(f for f in dataclasses.fields(cfg) if f.name == name)
    return dataclasses.replace(cfg, **{name: _checked(field, current, value, where)})


def check_tables(tables: dict, names: Iterable[str], *, source: str) -> None:
    """Refuse, naming `source` and the key, a value where one of the table `names` belongs (`mapper = 3` for
    a [mapper] table): it would otherwise reach the code that reads the table's options as a crash."""
    for name in names:
        if name in tables and not isinstance(tables[name], dict):
            raise InputError(f"{source}: {name!r} must be a table ([{name}] with its options on the lines "
                             f"below), got {tables[name]!r}")


def load_toml(path: Path | str) -> dict:
    """Read a TOML override file; a missing or malformed file is an InputError naming it."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(f"{path}: no such config file") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from None


def diff(old: dict, new: dict, prefix: str = "") -> list[str]:
    """Human-readable differences between two config dicts: ['sift.max_num_features: 8192 -> 4096', ...]."""
    out = []
    for key in sorted(set(old) | set(new)):
        name = f"{prefix}{key}"
        a, b = old.get(key, "<unset>"), new.get(key, "<unset>")
        if isinstance(a, dict) and isinstance(b, dict):
            out += diff(a, b, prefix=f"{name}.")
        elif a != b:
            out.append(f"{name}: {a} -> {b}")
    return out
