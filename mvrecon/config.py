"""Frozen-dataclass configs: plain-dict view, overrides from a dict or a TOML file, a stable hash, a readable diff.

Every stage takes a frozen dataclass (nested dataclasses allowed) with documented defaults. The workspace stores
`to_dict(config)` and `config_hash(config)` so that a rerun can tell whether its results may be mixed with the
ones already on disk. A field declared with `field(default=..., metadata={"hash": False})` (e.g. a worker count)
does not change results, so it is left out of the hash and of the stored dict.
"""

import dataclasses
import hashlib
import json
import tomllib
from pathlib import Path

from .errors import InputError


def _hashed_fields(cfg):
    return [f for f in dataclasses.fields(cfg) if f.metadata.get("hash", True)]


def to_dict(cfg, *, all_fields: bool = False) -> dict:
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


def config_hash(cfg_or_dict) -> str:
    """SHA-256 (16 hex digits) of the canonical JSON of a config: equal configs give equal hashes across runs."""
    d = cfg_or_dict if isinstance(cfg_or_dict, dict) else to_dict(cfg_or_dict)
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


def with_overrides(cfg, overrides: dict, *, source: str = "overrides"):
    """A copy of `cfg` with fields replaced from a (nested) dict; unknown keys raise InputError naming `source`."""
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
            changes[key] = tuple(value) if isinstance(value, list) else value
    return dataclasses.replace(cfg, **changes)


def load_toml(path) -> dict:
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
