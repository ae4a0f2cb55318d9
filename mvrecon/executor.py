"""A local process pool for per-item work (feature extraction), results yielded in the items' order.

Processes rather than threads because SIFT and RANSAC hold the GIL in their Python glue and because a crash in
native code then takes down one worker, not the run. While the parent has not loaded OpenCV, workers are plain
forks (instant, modules inherited). Once it has, they come from a `forkserver` that preloaded the heavy modules,
because forking a process whose OpenCV thread pool is running can deadlock. Each worker runs its native
libraries single-threaded (the pool already uses every core, and oversubscription only adds contention) and keeps
the memory it frees for its next item.
"""

import ctypes
import logging
import multiprocessing
import os
import resource
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager

_PRELOAD = ["numpy", "cv2", "mvrecon.features.sift"]  # what extraction workers need; no pycolmap
_SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
_set_here: set[str] = set()  # the variables one_blas_thread added to this process's environment
_context = None
_closed_workers_cpu = 0.0  # seconds used by the workers of closed pools (cpu_seconds)
_ending: list[threading.Thread] = []  # threads ending drained pools (WorkerPool.__exit__)
_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8  # glibc's mallopt parameters
_RESULT_PIPE_BYTES = 1 << 20


def peak_memory_mb() -> float:
    """This process's peak resident memory so far (MB); Linux reports ru_maxrss in KiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cpu_seconds() -> float:
    """User + system CPU time of this process (all its threads) and of the WorkerPool workers it has closed.
    The workers are counted from /proc when their pool closes: forkserver workers are not this process's
    children, so RUSAGE_CHILDREN would miss them."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    return own.ru_utime + own.ru_stime + _closed_workers_cpu


def _process_cpu_seconds(pid: int) -> float:
    """User + system CPU time of a live process (Linux /proc; 0 where there is none)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class StageClock:
    """Wall time, CPU time and peak memory per stage (report.json's `stages` and `total`). CPU over wall is the
    number of cores a stage kept busy: what bounds a run's speed on a small machine is its single-core part."""

    def __init__(self):
        self.stages = {}
        self._start = self._last = self._now()

    @staticmethod
    def _now() -> tuple[float, float]:
        return time.perf_counter(), cpu_seconds()

    @staticmethod
    def _between(start, end) -> dict:
        return {"wall_s": end[0] - start[0], "cpu_s": end[1] - start[1], "peak_mem_mb": peak_memory_mb()}

    def done(self, name: str) -> dict:
        """Record the stage that ends now (it began where the previous one ended; the clocks are read once, so
        consecutive stages add up to the whole)."""
        now = self._now()
        self.stages[name] = self._between(self._last, now)
        self._last = now
        return self.stages[name]

    def total(self) -> dict:
        return self._between(self._start, self._now())


def default_workers() -> int:
    """Cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


def one_blas_thread() -> None:
    """Every OpenBLAS this process loads (numpy's, and the copy OpenCV bundles) runs on the calling thread, unless
    the user set OPENBLAS_NUM_THREADS. Each reads it when it loads, so call this before numpy is imported. An
    OpenBLAS makes its extra thread again after every fork (the feature workers, and OpenCV's copy as they import
    it), and the thread spins 0.1 s each time on the cores the stages need; no stage gains from it (their products
    are small, or one per core already). templeSparseRing's reconstruct: 0.14 s less CPU, matching 0.03 s faster
    (docs/speed-log.md, session 28)."""
    if "OPENBLAS_NUM_THREADS" not in os.environ:
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
        _set_here.add("OPENBLAS_NUM_THREADS")


def user_environment() -> dict[str, str]:
    """This process's environment without what `one_blas_thread` added: the engines a comparison times run with
    the user's own settings."""
    return {k: v for k, v in os.environ.items() if k not in _set_here}


def _get_context():
    global _context
    if "cv2" not in sys.modules:
        # Nothing here has started OpenCV's thread pool yet, so plain fork is safe, and it is instant: the
        # workers inherit the loaded modules instead of importing them (~1 s saved per run on small sets).
        return multiprocessing.get_context("fork")
    if _context is None:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(_PRELOAD)
        # The forkserver inherits the environment at its start; BLAS reads these when numpy is first imported.
        saved = {k: os.environ.get(k) for k in _SINGLE_THREAD_ENV}
        os.environ.update(_SINGLE_THREAD_ENV)
        try:
            from multiprocessing import forkserver
            forkserver.ensure_running()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        _context = ctx
    return _context


def _init_worker():
    """Ctrl-C reaches the whole process group: only the parent acts on it, ending the pool (a worker raising
    KeyboardInterrupt itself printed a traceback, and could leave the pool waiting for it forever). The pool ends
    its workers with SIGTERM: they end quietly, not through a handler a library set in the parent (glog's, once
    pycolmap is loaded, prints a stack dump)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    import cv2

    cv2.setNumThreads(1)
    keep_freed_memory(one_arena=True)


def keep_freed_memory(one_arena: bool = False) -> None:
    """This process keeps the memory it frees for its next item instead of handing it back to the kernel.
    SIFT allocates and frees its scale space on every image (about 1 GB for a 3072 x 2048 photo, 80 MB for
    640 x 480), and glibc maps large blocks on their own and unmaps them when freed, or trims the heap's free top:
    each image then faulted all of that memory in again. herzjesu's features stage took 5.8-5.9 s instead of
    7.3-8.8 s, with the same peak memory (docs/frontend.md). The `mvrecon` process does the same: matching
    prepares each image's descriptors and their products in blocks of a few MB (templeSparseRing's matching
    stage: 15 ms faster). A no-op where the C library has no mallopt (not glibc).

    With `one_arena` (the feature workers) every thread allocates from the one heap. A worker's last image runs
    on every core's OpenCV thread (pipeline._extraction_jobs), and the extra thread took a malloc arena of its
    own, faulting in fresh memory while the main heap held the earlier images' free: herzjesu's features stage
    took 5.5-5.6 s instead of 4.9-5.1 s, and the process tree peaked 110 MB higher (docs/frontend.md). The
    mvrecon process keeps glibc's arenas: one arena there made templeSparseRing's run no faster."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return
    mallopt(_M_MMAP_MAX, 0)  # large blocks from the heap too, where freed memory is reused
    mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)  # and the heap never trimmed (the largest value mallopt takes)
    if one_arena:
        mallopt(_M_ARENA_MAX, 1)


def _widen_result_pipe(pool) -> None:
    """Let a worker hand over a whole result without waiting for the parent to read it. The workers share one
    pipe of 64 KB, less than one image's features (866 SIFT descriptors are 111 KB), and a worker writes it
    holding the pool's write lock: while the parent held its GIL (importing a library, writing the database),
    its result thread could not read, and both workers stood idle. The kernel caps the size at
    /proc/sys/fs/pipe-max-size (1 MB by default); elsewhere than Linux this is a no-op."""
    try:
        import fcntl

        with open("/proc/sys/fs/pipe-max-size") as f:
            size = min(_RESULT_PIPE_BYTES, int(f.read()))
        fcntl.fcntl(pool._outqueue._writer.fileno(), fcntl.F_SETPIPE_SZ, size)
    except (ImportError, AttributeError, OSError, ValueError):  # not Linux, or another Pool layout
        pass


class WorkerPool:
    """Up to `workers` processes, started when the pool is made: a caller that makes it, and calls `map`, before
    its own set-up (opening the database, probing images) overlaps that with the workers' start, their import
    of OpenCV and their first items. `map` yields `func(item)` for every item, in the items' order, so equal
    inputs give equal database rows (image ids) whatever the timing.

    `func` must be a module-level function and its result picklable; `func` should catch its own expected
    errors and return them as values, so one bad item does not end the whole map. Leaving the `with` block
    terminates the workers, as `multiprocessing.Pool`'s own does: after an exception or Ctrl-C in the consumer
    the items in flight are dropped and the workers are gone before it propagates; otherwise they end in a
    thread while the caller goes on (`wait_for_ended_pools`). With `workers <= 1` everything runs in the
    calling process, which keeps tracebacks simple and tests fast.
    """

    def __init__(self, workers: int | None = None):
        self.workers = default_workers() if workers is None else workers
        self._pool = None
        if self.workers > 1:
            wait_for_ended_pools()  # no fork while another thread works on a pool's queues
            ctx = _get_context()
            logging.getLogger(__name__).debug("process pool: %d %s workers", self.workers, ctx.get_start_method())
            self._pool = ctx.Pool(self.workers, initializer=_init_worker)
            _widen_result_pipe(self._pool)

    def map(self, func: Callable, items: Iterable) -> Iterator:
        """The items are handed to the workers now, not at the first `next`: the caller may do its own set-up
        while they run. In-process (`workers <= 1`), each item runs when its result is asked for."""
        if self._pool is None:
            return (func(item) for item in items)
        return self._pool.imap(func, items, chunksize=1)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        global _closed_workers_cpu
        if self._pool is not None:
            # multiprocessing.Pool keeps its worker processes in `_pool`; read them before they are ended
            _closed_workers_cpu += sum(_process_cpu_seconds(p.pid) for p in self._pool._pool)
            pool, self._pool = self._pool, None
            if exc[0] is not None:  # an error or Ctrl-C: the workers are gone before it propagates
                _end_pool(pool)
                return False
            # A drained pool ends in a thread while the caller goes on: ending the workers waits for the kernel to
            # free their memory (10-13 ms on templeSparseRing, while the next stage's set-up ran on one core).
            # A non-daemon thread: the interpreter's exit, or the next pool, waits for it.
            thread = threading.Thread(target=_end_pool, args=(pool,), name="end-worker-pool")
            thread.start()
            _ending.append(thread)
        return False


def _end_pool(pool) -> None:
    pool.terminate()
    pool.join()


def wait_for_ended_pools() -> None:
    """Wait until every pool that WorkerPool left to end in a thread has ended."""
    while _ending:
        _ending.pop().join()


def _openblas_controls():
    """(get, set) thread-count functions of every OpenBLAS this process has loaded (numpy's, scipy's)."""
    try:
        with open("/proc/self/maps", errors="surrogateescape") as fh:  # mapped files may have any bytes in their names
            paths = sorted({line.split()[-1] for line in fh if "openblas" in line.lower() and "/" in line})
    except OSError:
        return []
    controls = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix, suffix in (("scipy_openblas", "64_"), ("scipy_openblas", ""),
                               ("openblas", "64_"), ("openblas", "")):
            get, set_ = f"{prefix}_get_num_threads{suffix}", f"{prefix}_set_num_threads{suffix}"
            if hasattr(lib, get) and hasattr(lib, set_):
                controls.append((getattr(lib, get), getattr(lib, set_)))
                break
    return controls


@contextmanager
def blas_threads(n: int):
    """Run the block with BLAS limited to `n` threads. When the caller already runs one task per core, BLAS's
    own threads only compete with them, and OpenBLAS threads spin while they wait: on a busy 2-core machine
    descriptor matching ran 3x slower with them than without."""
    controls = _openblas_controls()
    saved = [get() for get, _ in controls]
    for _, set_ in controls:
        set_(int(n))
    try:
        yield
    finally:
        for (_, set_), value in zip(controls, saved):
            set_(int(value))
