"""The record of the work finished in a folder, so that a rerun (after Ctrl-C, a bad input, or with some
settings changed) redoes only what is missing, and results made with different settings are never mixed.

`FOLDER/.stages/NAME.json` (JSON) holds, for each named piece of work (a stage, an image, a pair, an engine's
run), in the order first recorded: its key (a hash of everything it was computed from: input pixels, settings,
the code of the modules doing the work; `digest`, `code_digest`, or `config.config_hash` of its settings), its
JSON-able report, the seconds it took and, when the caller keeps them, the settings the key was made from (so
that a refusal can name the fields that differ: `differences`). A piece is redone when its key differs or one
of its files is missing. Its entry is dropped before its files are rewritten, and every file (the record too)
is written whole (`io.files`), so a piece cut off by Ctrl-C is never taken for a finished one.

Who keeps which record: a workspace its stages (`workspace.Workspace`, which refuses a changed config instead
of redoing it); `stereo` its stages in its output folder; `detectors` and `calibrate` one per output file (its
images, its pairs), next to it; the engine runners one per run folder (`eval.runners`); a scene its views
(`scenes.catalog`); a study its settings and its cells' images (`study.study`).
"""

import hashlib
import importlib.util
import json
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ..config import config_hash, diff
from .files import read_json_object, write_json

FOLDER = ".stages"  # in the folder whose work is recorded


def digest(*parts) -> str:
    """sha256 of arrays (shape, dtype, bytes) and JSON-able settings, in order."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(f"{part.shape} {part.dtype}".encode())
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(json.dumps(part, sort_keys=True, default=str).encode())
    return h.hexdigest()


def code_digest(*modules: str) -> str:
    """Hash of the modules' source files: an edited method must not reuse an older run's results."""
    return digest([Path(importlib.util.find_spec(m).origin).read_text() for m in modules])


def _valid(entry) -> bool:
    return (isinstance(entry, dict) and isinstance(entry.get("key"), str)
            and isinstance(entry.get("report", {}), dict) and isinstance(entry.get("config", {}), dict))


class Record:
    """The record of the work finished in `folder` (see the module's docstring), read when made. `reused`
    lists the names taken from the record in this run, in order; `used` every name asked for. `damaged`: the
    file is there but is not a record (edited by hand, or another tool's): its valid entries are kept, and a
    caller that cannot redo its work without knowing what it was made with refuses it."""

    def __init__(self, folder: str | Path, name: str = "record.json") -> None:
        self.out = Path(folder)
        self.path = self.out / FOLDER / name
        data = read_json_object(self.path)
        self.damaged = self.path.exists() and (data is None or not all(_valid(e) for e in data.values()))
        self.entries: dict[str, dict] = {n: e for n, e in (data or {}).items() if _valid(e)}
        self.reused: list[str] = []
        self.used: set[str] = set()

    def names(self) -> list[str]:
        """The names recorded, in the order they were first recorded."""
        return list(self.entries)

    def key(self, name: str) -> str | None:
        entry = self.entries.get(name)
        return None if entry is None else entry["key"]

    def report(self, name: str) -> dict | None:
        """The report recorded for `name` (None when not recorded), whatever its key and files."""
        entry = self.entries.get(name)
        return None if entry is None else entry.get("report", {})

    def config(self, name: str) -> dict | None:
        """The settings `name` was recorded with (None when not recorded, or recorded without them)."""
        entry = self.entries.get(name)
        return None if entry is None else entry.get("config")

    def run(self, name: str, key: str, files: Iterable, make: Callable[[], dict | None]) -> dict:
        """make() writes `files` (in the folder) and returns the piece's report, or the record has it."""
        report = self.get(name, key, files)
        if report is not None:
            return report
        self.drop(name)
        t0 = time.perf_counter()
        report = make() or {}
        self.put(name, key, report, time.perf_counter() - t0)
        return report

    def get(self, name: str, key: str, files: Iterable = ()) -> dict | None:
        """The report recorded for `name` under `key` when its files are all there (counted as reused), else
        None."""
        self.used.add(name)
        entry = self.entries.get(name)
        if entry is not None and entry["key"] == key and all((self.out / f).is_file() for f in files):
            self.reused.append(name)
            return entry.get("report", {})
        return None

    def differences(self, name: str, config: dict) -> list[str]:
        """The fields (`config.diff`) in which `config` differs from the settings `name` was recorded with,
        as 'field: old -> new'; [] when `name` is not recorded or has the same key (`config.config_hash`). A
        piece recorded without its settings differs in an unnamed way: ['(settings not recorded)']."""
        entry = self.entries.get(name)
        if entry is None or entry["key"] == config_hash(config):
            return []
        return diff(entry["config"], config) if "config" in entry else ["(settings not recorded)"]

    def drop(self, *names: str) -> None:
        """Forget the pieces `names` (on disk too) before their files are rewritten."""
        if [self.entries.pop(name) for name in names if name in self.entries]:
            self.write()

    def put(self, name: str, key: str, report: dict | None = None, seconds: float = 0.0,
            config: dict | None = None) -> None:
        """Record `name` as finished under `key` (with the settings `config` it was made from, when given)."""
        self.used.add(name)
        entry = {"key": key, "report": report or {}, "seconds": seconds}
        if config is not None:
            entry["config"] = config
        self.entries[name] = entry
        self.write()

    def seconds(self, name: str) -> float:
        return float(self.entries[name]["seconds"])

    def prune(self) -> None:
        """Drop the entries this run did not ask for (other images, settings no longer used), so that the
        record of an output rewritten many times does not grow without end."""
        stale = [n for n in self.entries if n not in self.used]
        for name in stale:
            del self.entries[name]
        if stale:
            self.write()

    def clear(self) -> None:
        """Forget every piece (and a damaged file's content)."""
        self.entries = {}
        self.damaged = False
        self.write()

    def write(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_json(self.path, self.entries, indent=1)
