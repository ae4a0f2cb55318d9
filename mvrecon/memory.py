"""Memory of a run: the peak of its process tree (the process and its workers), the main process's own peak,
and the memory free for more work.

One definition serves report.json and `mvrecon compare`'s runners alike: the peak memory of a run is the
largest sum of the resident memory (RSS) of its processes, sampled every `INTERVAL_S` by a `PeakSampler`, and
never less than the main process's own peak (`main_peak_mb`, the kernel's exact high-water mark, which a
sample can miss). RSS counts a page shared by two processes (a forked worker's copy of its parent's libraries)
in both, as `ps` and `top` do. The feature workers keep the memory they free (startup.keep_freed_memory), so
their RSS only grows and sampling does not miss their peaks.
"""

import os
import resource
import threading
from collections.abc import Callable, Iterable

INTERVAL_S = 0.2
_PAGE = os.sysconf("SC_PAGE_SIZE")


def main_peak_mb() -> float:
    """This process's peak resident memory so far (MB): the kernel's high-water mark of its own memory (VmHWM).

    Not ru_maxrss: Linux carries that over an exec from the process that started this one, so mvrecon started
    from a notebook or a test run holding 800 MB reported 800 MB for itself. ru_maxrss (KiB on Linux) serves
    only where /proc is missing."""
    peak = _proc_mb("/proc/self/status", b"VmHWM:")
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0 if peak is None else peak


def rss_mb(pids: Iterable[int]) -> float:
    """Summed resident memory of the processes (MB), read from /proc (40 us a process, where psutil's listing
    of a process's children reads every process on the machine: 10 ms); processes that have ended count 0."""
    pages = 0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/statm", "rb") as fh:
                pages += int(fh.read().split()[1])
        except (OSError, ValueError, IndexError):
            pass
    return pages * _PAGE / 2 ** 20


def process_tree(pid: int) -> list[int]:
    """`pid` and every process below it (psutil; 10 ms on a machine running 100 processes)."""
    import psutil  # noqa: PLC0415 - 0.1-0.5 s of import, for the engines a comparison times only

    try:
        root = psutil.Process(pid)
        return [pid, *(p.pid for p in root.children(recursive=True))]
    except psutil.Error:
        return [pid]


def available_mb() -> float:
    """Memory the kernel can give without swapping (MB): free memory plus caches it can drop (MemAvailable,
    what psutil.virtual_memory().available reads; read here directly, as importing psutil took 0.1-0.5 s)."""
    available = _proc_mb("/proc/meminfo", b"MemAvailable:")
    if available is not None:
        return available
    import psutil  # noqa: PLC0415 - not Linux; 0.1-0.5 s of import that a run on Linux never spends

    return psutil.virtual_memory().available / 2 ** 20


def _proc_mb(path: str, key: bytes) -> float | None:
    """The value (MB) of the line `key` of a /proc file that gives it in kB, or None where there is none."""
    try:
        with open(path, "rb") as fh:
            for line in fh:
                if line.startswith(key):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return None


class PeakSampler:
    """The largest summed RSS of `pids()` (MB), sampled every `interval` s in a thread from `start()` to
    `stop()`. `pids` is called at every sample, so processes that start later are counted from then on."""

    def __init__(self, pids: Callable[[], Iterable[int]], interval: float = INTERVAL_S):
        self._pids, self._interval = pids, interval
        self.peak_mb = 0.0
        self._stop = threading.Event()
        self._thread = None

    def sample(self) -> float:
        now = rss_mb(self._pids())
        self.peak_mb = max(self.peak_mb, now)
        return now

    def start(self) -> "PeakSampler":
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="memory-sampler", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> float:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None
        return self.peak_mb

    def _run(self) -> None:
        while True:
            self.sample()
            if self._stop.wait(self._interval):
                return
