"""Work finished by earlier runs, so that a rerun (after Ctrl-C, a bad input, or with some settings changed) redoes
only what is missing.

`FOLDER/.stages/RECORD` (JSON) holds, for each named piece of work (a stage, an image, a pair), its key: a hash of
everything it was computed from (input pixels, settings, the code of the modules doing the work; `digest`,
`code_digest`), its JSON-able report and the seconds it took when it was computed. A piece is redone when its key
differs or one of its files is missing. Its entry is dropped before its files are rewritten, and every file (the
record too) is written whole (`io.files`), so a piece cut off by Ctrl-C is never taken for a finished one.

`stereo` keeps one record of its stages in its output folder; `detectors` and `calibrate` keep one per output file
(its images, its pairs), next to it.
"""

import hashlib
import importlib.util
import json
import time
from pathlib import Path

import numpy as np

from .files import read_json_object, write_json


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


def code_digest(*modules) -> str:
    """Hash of the modules' source files: an edited method must not reuse an older run's results."""
    return digest([Path(importlib.util.find_spec(m).origin).read_text() for m in modules])


class Stages:
    """The record of the work finished in `folder` (see the module's docstring). `reused` lists the names taken
    from the record in this run, in order."""

    def __init__(self, folder, record: str = "record.json"):
        self.out = Path(folder)
        self.path = self.out / ".stages" / record
        self.record = read_json_object(self.path) or {}
        self.reused: list[str] = []
        self.used: set[str] = set()

    def run(self, name: str, key: str, files, make) -> dict:
        """make() writes `files` (in the folder) and returns the piece's report entries, or the record has them."""
        report = self.get(name, key, files)
        if report is not None:
            return report
        self.drop(name)
        t0 = time.perf_counter()
        report = make() or {}
        self.put(name, key, report, time.perf_counter() - t0)
        return report

    def get(self, name: str, key: str, files=()) -> dict | None:
        """The report recorded for `name` under `key` when its files are all there (counted as reused), else None."""
        self.used.add(name)
        entry = self.record.get(name)
        if isinstance(entry, dict) and entry.get("key") == key and all((self.out / f).is_file() for f in files):
            self.reused.append(name)
            report = entry.get("report")
            return report if isinstance(report, dict) else {}
        return None

    def drop(self, name: str) -> None:
        """Forget `name` (on disk too) before its files are rewritten."""
        if self.record.pop(name, None) is not None:
            self._write()

    def put(self, name: str, key: str, report: dict, seconds: float) -> None:
        self.used.add(name)
        self.record[name] = {"key": key, "report": report, "seconds": seconds}
        self._write()

    def seconds(self, name: str) -> float:
        return float(self.record[name]["seconds"])

    def prune(self) -> None:
        """Drop the entries this run did not ask for (other images, settings no longer used), so that the record
        of an output rewritten many times does not grow without end."""
        stale = [n for n in self.record if n not in self.used]
        for name in stale:
            del self.record[name]
        if stale:
            self._write()

    def _write(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_json(self.path, self.record, indent=1)
