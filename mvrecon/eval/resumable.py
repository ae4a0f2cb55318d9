"""The stages of a COLMAP reference run, resumable: a 1,000-image run takes COLMAP hours, longer than a machine may
be left to it, so a run that is cut off (Ctrl-C, a killed process, the machine's end of day) goes on next time
from what it had done, and each stage's time is counted once.

- features and matching write to the run's database as they go, and pycolmap's extract_features and matchers
  skip the images and pairs already there, so their time counts up to the last heartbeat (every `HEARTBEAT_S`);
- incremental mapping writes a snapshot of its model every `SNAPSHOT_FRAMES` registered images and resumes from
  the newest whole one (`SnapshotSealer`); its time counts up to that snapshot, the work after it being done
  again.
  Global mapping has no snapshots: an attempt cut off counts nothing and the next one maps again from the start.

So a resumed run's stage times are those of one run without its repeated work, less at most a heartbeat per
attempt, and never more than an uninterrupted run's: a comparison against it errs in COLMAP's favour. The record
(OUT/`PROGRESS`) holds, per stage, the counted wall and CPU seconds, the peak memory and whether it is done, and
the attempts made; a record of another pycolmap version is dropped, and the run starts again.
"""

import shutil
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pycolmap

from ..executor import cpu_seconds, tree_peak_memory_mb
from ..io.files import read_json_object, write_json

PROGRESS = "colmap-progress.json"
HEARTBEAT_S = 10.0
SNAPSHOT_FRAMES = 100


class StageProgress:
    """The record of a resumable run in OUT: `stage(name)` runs a stage unless it is done, and counts its time."""

    def __init__(self, out_dir: Path | str):
        self.path = Path(out_dir) / PROGRESS
        data = read_json_object(self.path) or {}
        if data.get("pycolmap") != pycolmap.__version__:
            data = {}
        self.resumed = bool(data.get("stages"))
        self.data = {"pycolmap": pycolmap.__version__, "attempts": int(data.get("attempts", 0)) + 1,
                     "stages": data.get("stages", {})}
        self._lock = threading.Lock()
        self._save()

    def done(self, name: str) -> bool:
        return bool(self.data["stages"].get(name, {}).get("done"))

    def snapshot(self, name: str) -> Path | None:
        """The newest whole snapshot an earlier attempt of stage `name` wrote, or None."""
        path = self.data["stages"].get(name, {}).get("snapshot")
        return Path(path) if path and Path(path).is_dir() else None

    @contextmanager
    def stage(self, name: str, snapshots: Path | None = None) -> Iterator[None]:
        """Time the stage run inside the `with` block; its counted time grows with heartbeats while it runs, and
        is whole when the block ends. With `snapshots` (the folder the stage writes snapshots to) it grows only
        to the newest whole snapshot, which the record keeps (`snapshot`). Callers skip the block when
        `done(name)`."""
        entry = self.data["stages"].setdefault(name, {"wall_s": 0.0, "cpu_s": 0.0, "peak_mem_mb": 0.0,
                                                      "done": False})
        base_wall, base_cpu = entry["wall_s"], entry["cpu_s"]
        start_wall, start_cpu, start_time = time.perf_counter(), cpu_seconds(), time.time()
        sealer = SnapshotSealer(snapshots, since=start_time) if snapshots is not None else None

        def count(whole: bool) -> None:
            with self._lock:
                wall, cpu = time.perf_counter() - start_wall, cpu_seconds() - start_cpu
                if not whole and sealer is not None:
                    sealed = sealer.check()
                    if sealed is not None:
                        entry["snapshot"] = str(sealed)
                    until = sealer.sealed_time
                    share = 0.0 if until is None else min(1.0, max(0.0, until - start_time) / max(wall, 1e-9))
                    wall, cpu = wall * share, cpu * share
                entry.update(wall_s=base_wall + wall, cpu_s=base_cpu + cpu, done=whole,
                             peak_mem_mb=max(entry["peak_mem_mb"], tree_peak_memory_mb()))
                self._save()

        stop = threading.Event()
        beat = threading.Thread(target=lambda: [count(False) for _ in iter(lambda: stop.wait(HEARTBEAT_S), True)],
                                daemon=True, name=f"progress-{name}")
        beat.start()
        try:
            yield
        finally:
            stop.set()
            beat.join()
        count(True)

    def stages(self) -> dict:
        """report.json's `stages`: the counted time of each stage over all attempts."""
        return {name: {k: e[k] for k in ("wall_s", "cpu_s", "peak_mem_mb")} for name, e in self.data["stages"].items()}

    def total(self) -> dict:
        """report.json's `total`: the stages' counted times summed, their peak memory the largest."""
        return {**_summed(self.data["stages"]), "attempts": self.data["attempts"]}

    def _save(self) -> None:
        write_json(self.path, self.data, indent=1)


class SnapshotSealer:
    """Tells the whole snapshots in a folder the mapper writes them to: the newest one written since `since` (the
    attempt's start) is whole once its files are the same at two checks made while the mapper lives (a mapper
    writes a snapshot in one go and goes on), so that one cut off while it was written is never taken. Reading a
    cut-off model back is no test: pycolmap may read a garbage track length there and allocate without end. The
    snapshots older than the newest whole one are deleted, which bounds the disk they take."""

    def __init__(self, folder: Path, since: float = 0.0):
        self.folder, self.since = Path(folder), since
        self.sealed: Path | None = None
        self.sealed_time: float | None = None  # the `time.time()` the sealed snapshot was written
        self._seen: tuple | None = None

    def check(self) -> Path | None:
        """The snapshot sealed by this call, or None."""
        snaps = sorted((p for p in self.folder.iterdir() if p.is_dir()), key=lambda p: p.stat().st_mtime) \
            if self.folder.is_dir() else []
        if not snaps or snaps[-1] == self.sealed or snaps[-1].stat().st_mtime < self.since:
            return None
        newest = snaps[-1]
        files = tuple(sorted((f.name, f.stat().st_size, f.stat().st_mtime_ns) for f in newest.iterdir()))
        seen, self._seen = self._seen, (newest, files)
        if seen != (newest, files) or not any(name == "points3D.bin" for name, _, _ in files):
            return None
        self.sealed = newest
        self.sealed_time = max(mtime for _, _, mtime in files) / 1e9
        for old in snaps[:-1]:
            shutil.rmtree(old, ignore_errors=True)
        return newest


def counted_before(out_dir: Path | str) -> tuple[float, float]:
    """(seconds, peak MB) that earlier attempts of the run in OUT counted, (0, 0) for a run that starts now: what
    the caller adds to the wall time and memory it measures of the next attempt."""
    data = read_json_object(Path(out_dir) / PROGRESS) or {}
    if data.get("pycolmap") != pycolmap.__version__:
        return 0.0, 0.0
    total = _summed(data.get("stages", {}))
    return total["wall_s"], total["peak_mem_mb"]


def _summed(stages: dict) -> dict:
    """The stages' counted wall and CPU seconds summed, and their largest peak memory."""
    entries = stages.values()
    return {"wall_s": sum(e.get("wall_s", 0.0) for e in entries), "cpu_s": sum(e.get("cpu_s", 0.0) for e in entries),
            "peak_mem_mb": max((e.get("peak_mem_mb", 0.0) for e in entries), default=0.0)}
