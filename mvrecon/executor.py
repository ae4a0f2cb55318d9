"""A local process pool for per-item work (feature extraction), results yielded in the items' order.

Processes rather than threads because SIFT and RANSAC hold the GIL in their Python glue and because a crash in
native code then takes down one worker, not the run: the pool notices a worker's end at once, runs its item
again in a fresh worker, and gives it up with the reason if that worker dies too (WorkerPool). While the
parent has not loaded OpenCV, workers are plain forks (instant, modules inherited). Once it has, they come
from a `forkserver`, because forking a process whose OpenCV thread pool is running can deadlock. Each worker
runs its native libraries single-threaded (the pool already uses every core, and oversubscription only adds
contention) and keeps the memory it frees for its next item (startup.keep_freed_memory).
"""

import ctypes
import fcntl
import logging
import multiprocessing
import multiprocessing.connection
import os
import resource
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing import forkserver
from typing import TypeVar

from .memory import PeakSampler, available_mb, main_peak_mb
from .startup import keep_freed_memory

log = logging.getLogger(__name__)
T = TypeVar("T")

_SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
_set_here: set[str] = set()  # the variables one_blas_thread added to this process's environment
_context = None
_closed_workers_cpu = 0.0  # seconds used by the workers of closed pools (cpu_seconds)
_ending: list[threading.Thread] = []  # threads ending drained pools (WorkerPool.__exit__)
_RESULT_PIPE_BYTES = 1 << 20


def cpu_seconds() -> float:
    """User + system CPU time of this process (all its threads) and of the WorkerPool workers it has closed.
    The workers are counted from /proc when their pool closes: forkserver workers are not this process's
    children, so RUSAGE_CHILDREN would miss them."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    return own.ru_utime + own.ru_stime + _closed_workers_cpu


def process_cpu_seconds(pid: int) -> float:
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
        """`peak_mem_mb`: the peak of this process and its workers so far (tree_peak_memory_mb);
        `peak_main_mem_mb`: this process's alone."""
        return {"wall_s": end[0] - start[0], "cpu_s": end[1] - start[1], "peak_mem_mb": tree_peak_memory_mb(),
                "peak_main_mem_mb": main_peak_mb()}

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
    are small, or one per core already). templeSparseRing's reconstruct takes 0.14 s less CPU with it."""
    if "OPENBLAS_NUM_THREADS" not in os.environ:
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
        _set_here.add("OPENBLAS_NUM_THREADS")


def in_background(func: Callable[[], T]) -> "Future[T]":
    """`func()` started now in a thread of its own, its result (or what it raised) in the returned future. The
    thread is a daemon, so that Ctrl-C ends the process without waiting for it. Worth it where `func` spends its
    time in code that lets go of the GIL (compiled loops, LAPACK) while the caller works beside it."""
    future: Future = Future()

    def run() -> None:
        future.set_running_or_notify_cancel()
        try:
            future.set_result(func())
        except BaseException as exc:  # handed to the caller, who decides
            future.set_exception(exc)

    threading.Thread(target=run, name=getattr(func, "__name__", "background"), daemon=True).start()
    return future


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
        _ensure_forkserver()
        _context = ctx
    return _context


def _ensure_forkserver() -> None:
    """Start the forkserver unless it runs (again, if it has died). It inherits the environment at its start;
    BLAS reads these when numpy is first imported."""
    saved = {k: os.environ.get(k) for k in _SINGLE_THREAD_ENV}
    os.environ.update(_SINGLE_THREAD_ENV)
    try:
        forkserver.ensure_running()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _init_worker():
    """Ctrl-C reaches the whole process group: only the parent acts on it, ending the pool (a worker raising
    KeyboardInterrupt itself printed a traceback, and could leave the pool waiting for it forever). The pool ends
    its workers with SIGTERM: they end quietly, not through a handler a library set in the parent (glog's, once
    pycolmap is loaded, prints a stack dump)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    import cv2  # noqa: PLC0415 - here, in the worker: the parent forks its workers before loading OpenCV

    cv2.setNumThreads(1)
    keep_freed_memory(one_arena=True)


def _widen_pipe(conn) -> None:
    """Let a worker hand over a whole result without waiting for the parent to read it: a pipe holds 64 KB,
    less than one image's features (866 SIFT descriptors are 111 KB), and while the parent held its GIL
    (importing a library, writing the database) its pool thread could not read, and the workers stood idle.
    The kernel caps the size at /proc/sys/fs/pipe-max-size (1 MB by default); elsewhere than Linux this is a
    no-op."""
    try:
        with open("/proc/sys/fs/pipe-max-size") as f:
            size = min(_RESULT_PIPE_BYTES, int(f.read()))
        fcntl.fcntl(conn.fileno(), fcntl.F_SETPIPE_SZ, size)
    except (ImportError, AttributeError, OSError, ValueError):  # not Linux
        pass


class WorkerDied(RuntimeError):
    """The worker processes running an item died twice (WorkerPool.map without `died`)."""


def describe_death(exitcode: int | None) -> str:
    """How a process ended, for a user: 'signal 9 (SIGKILL), probably out of memory' (what the kernel's
    out-of-memory killer sends), 'signal 11 (SIGSEGV), a crash in native code', or 'exit code N'."""
    if exitcode is None or exitcode >= 0:
        return f"exit code {exitcode}"
    number = -exitcode
    try:
        text = f"signal {number} ({signal.Signals(number).name})"
    except ValueError:
        return f"signal {number}"
    if number == signal.SIGKILL:
        return text + ", probably out of memory"
    if number in (signal.SIGSEGV, signal.SIGBUS, signal.SIGILL, signal.SIGFPE, signal.SIGABRT):
        return text + ", a crash in native code"
    return text


def _work(tasks, results) -> None:
    """A worker: run the jobs its pipe brings, `(job id, func, item)`, until the pipe closes or brings None,
    and send back `(job id, True, result)` or `(job id, False, exception)`."""
    _init_worker()
    while True:
        try:
            task = tasks.recv()
        except (EOFError, OSError):
            return
        if task is None:
            return
        job_id, func, item = task
        try:
            out = (job_id, True, func(item))
        except Exception as exc:  # noqa: BLE001 - the caller gets it where it asks for this item's result
            out = (job_id, False, exc)
        try:
            results.send(out)
        except (EOFError, OSError):  # the parent has gone
            return
        except Exception as exc:  # noqa: BLE001 - a result or an error that cannot be pickled
            results.send((job_id, False, RuntimeError(f"{type(exc).__name__}: {exc}")))


@dataclass(eq=False)
class _Job:
    func: Callable
    item: object
    name: Callable | None  # item -> text for messages
    cost: Callable | None  # item -> MB a worker needs for it
    died: Callable | None  # (item, why) -> the result given for an item whose workers died twice
    cost_mb: float | None = None  # cost(item), computed when the job is first considered
    deaths: int = 0
    alone: bool = False  # a retry: it runs with nothing else in flight, in a fresh worker


class _Worker:
    """One worker process with its own pipes: the pool knows which jobs each worker holds, so a worker that
    dies costs only those, and no lock shared with the other workers is left held (a worker of
    `multiprocessing.Pool` killed while it waited for a task, or wrote a result, held the lock of the queue
    every worker shares, and the whole pool stood still)."""

    def __init__(self, ctx):
        tasks_out, self.tasks = multiprocessing.Pipe(duplex=False)
        self.results, results_in = multiprocessing.Pipe(duplex=False)
        _widen_pipe(results_in)
        self.process = ctx.Process(target=_work, args=(tasks_out, results_in), daemon=True)
        self.process.start()
        tasks_out.close()  # the worker's ends: the parent sees the worker's end as the end of its pipe
        results_in.close()
        self.queue: deque[int] = deque()  # ids of the jobs sent and not answered, the running one first
        self.held_mb = 0.0  # the largest cost of the jobs it was sent: it keeps the memory it frees
        self.ran = 0  # jobs answered
        self.broken = False  # its pipe refused a job: it has ended, and its sentinel will say how

    def close(self) -> None:
        self.tasks.close()
        self.results.close()


_pools: list["WorkerPool"] = []  # pools whose workers are alive, for the memory sampler
_tree = PeakSampler(lambda: [os.getpid(), *_helper_pids(), *(w.process.pid for p in list(_pools)
                                                             for w in list(p._live))])


def _helper_pids() -> list[int]:
    """The processes multiprocessing started for the pools: the forkserver and its resource tracker."""
    pids = []
    for module, holder, attr in (("multiprocessing.forkserver", "_forkserver", "_forkserver_pid"),
                                 ("multiprocessing.resource_tracker", "_resource_tracker", "_pid")):
        pid = getattr(getattr(sys.modules.get(module), holder, None), attr, None)
        if pid:
            pids.append(pid)
    return pids


def tree_peak_memory_mb() -> float:
    """The peak memory of this process and its workers so far (MB), as memory.py defines it: the largest
    summed RSS sampled while a WorkerPool had workers, and at least this process's own peak."""
    return max(_tree.peak_mb, main_peak_mb())


class WorkerPool:
    """Up to `workers` processes, started when the pool is made: a caller that makes it, and calls `map`, before
    its own set-up (opening the database, probing images) overlaps that with the workers' start, their import
    of OpenCV and their first items. `map` yields `func(item)` for every item, in the items' order, so equal
    inputs give equal database rows (image ids) whatever the timing.

    `func` must be a module-level function and its result picklable; `func` should catch its own expected
    errors and return them as values, so one bad item does not end the whole map (an exception it raises is
    raised where the caller asks for that item's result). A worker that dies (SIGKILL from the kernel's
    out-of-memory killer, SIGSEGV from a crash in native code) is noticed at once, through its process's
    sentinel: its item runs again, alone and in a fresh worker, and if that worker dies too the item's result
    is `died(item, why)` (why: `describe_death`), or WorkerDied is raised for it; the other items go on.
    Leaving the `with` block terminates the workers: after an exception or Ctrl-C in the consumer the items in
    flight are dropped and the workers are gone before it propagates; otherwise they end in a thread while the
    caller goes on (`wait_for_ended_pools`). With `workers <= 1` everything runs in the calling process, which
    keeps tracebacks simple and tests fast (and a crash there ends the run); so it does in a daemon process (a
    worker of another pool, e.g. a part of a partitioned mapping), which may not start processes of its own.

    Each worker holds at most two jobs, the one it runs and the next, so it goes on while the parent holds its
    GIL; the last `workers` jobs go only to idle workers, so that none waits behind another's job while a
    worker stands idle.
    """

    def __init__(self, workers: int | None = None):
        self.workers = default_workers() if workers is None else workers
        if multiprocessing.current_process().daemon:
            self.workers = 1
        self._live: list[_Worker] = []
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._jobs: dict[int, _Job] = {}
        self._pending: deque[int] = deque()  # job ids not yet sent, in order
        # job id -> (True, result), (False, the exception it raised) or (None, why its workers died)
        self._done: dict[int, tuple] = {}
        self._next_id = 0
        self._budget_mb = None  # memory the jobs' costs may add up to (`map`'s `cost`)
        self._closing = False
        self._error = None  # what ended the pool's thread, raised to the consumer
        self._dead_cpu = 0.0
        self._thread = None
        if self.workers > 1:
            wait_for_ended_pools()  # no fork while another thread ends a pool's workers
            ctx = _get_context()
            log.debug("process pool: %d %s workers", self.workers, ctx.get_start_method())
            self._live = [_Worker(ctx) for _ in range(self.workers)]
            self._wake_r, self._wake_w = os.pipe()
            self._thread = threading.Thread(target=self._watch, name="worker-pool", daemon=True)
            self._thread.start()
            _pools.append(self)
            if len(_pools) == 1:
                _tree.start()

    def pids(self) -> list[int]:
        """The process ids of the live workers."""
        with self._lock:
            return [w.process.pid for w in self._live]

    def map(self, func: Callable, items: Iterable, *, name: Callable | None = None,
            cost: Callable | None = None, died: Callable | None = None) -> Iterator:
        """The items are handed to the workers now, not at the first `next`: the caller may do its own set-up
        while they run. In-process (`workers <= 1`), each item runs when its result is asked for.

        `name(item)` names an item in the warning about a dead worker. `cost(item)` is the memory (MB) a
        worker needs for the item: items run at the same time only while the largest cost each worker has had
        (it keeps the memory it frees) adds up to no more than the memory available when the first such map
        began; one item always runs. `died(item, why)` is the result of an item whose workers died twice."""
        if self._thread is None:
            return (func(item) for item in items)
        with self._lock:
            if cost is not None and self._budget_mb is None:
                self._budget_mb = available_mb()
            ids = []
            for item in items:
                ids.append(self._next_id)
                self._jobs[self._next_id] = _Job(func, item, name, cost, died)
                self._pending.append(self._next_id)
                self._next_id += 1
            self._dispatch()
        os.write(self._wake_w, b".")  # the pool's thread watches workers this may have started
        return self._results(ids)

    def _results(self, ids) -> Iterator:
        for job_id in ids:
            with self._lock:
                while job_id not in self._done:
                    if self._error is not None:
                        raise RuntimeError("the process pool's thread failed") from self._error
                    self._changed.wait()
                ok, value = self._done.pop(job_id)
                job = self._jobs.pop(job_id)
            if ok is None:
                if job.died is None:
                    raise WorkerDied(f"the workers running {_name(job)} died: {value}")
                value = job.died(job.item, value)
            elif not ok:
                raise value
            yield value

    def _dispatch(self) -> None:
        """Send the pending jobs, in order, to the workers that may take them (the lock held)."""
        while self._pending and not self._closing:
            job = self._jobs[self._pending[0]]
            if job.cost is not None and job.cost_mb is None:
                job.cost_mb = float(job.cost(job.item))
            worker = self._worker_for(job)
            if worker is None:
                return
            job_id = self._pending.popleft()
            try:
                worker.tasks.send((job_id, job.func, job.item))
            except OSError:  # it has ended: its sentinel will say how; the job goes to another worker
                worker.broken = True
                self._pending.appendleft(job_id)
                continue
            worker.queue.append(job_id)
            worker.held_mb = max(worker.held_mb, job.cost_mb or 0.0)

    def _worker_for(self, job: _Job) -> "_Worker | None":
        """The worker to send `job` to now, or None to wait (the lock held)."""
        while len(self._live) < self.workers:  # dead workers are replaced while jobs wait
            try:
                self._live.append(self._new_worker())
            except OSError as exc:  # out of memory or processes: go on with the workers left
                if not self._live:
                    raise
                log.warning("cannot start a worker process (%s); going on with %d", exc, len(self._live))
                self.workers = len(self._live)
        usable = [w for w in self._live if not w.broken]
        busy = sum(len(w.queue) for w in usable)
        if any(self._jobs[j].alone for w in usable for j in w.queue):
            return None  # a retry runs on its own
        if job.alone:  # a retry: nothing else in flight, and a worker that has run nothing
            if busy or not usable:
                return None
            fresh = [w for w in usable if w.ran == 0 and w.held_mb == 0]
            if fresh:
                return fresh[0]
            self._live.remove(usable[0])
            self._dead_cpu += process_cpu_seconds(usable[0].process.pid)
            _end_pool([usable[0]])
            worker = self._new_worker()
            self._live.append(worker)
            return worker
        candidates = [w for w in usable if not w.queue]
        if len(self._pending) > len(usable):  # a second job for a busy worker, but never one of the last ones
            candidates += [w for w in usable if len(w.queue) == 1]
        if job.cost_mb is not None and self._budget_mb is not None:
            total = sum(w.held_mb for w in usable)

            def after(w):
                return total - w.held_mb + max(w.held_mb, job.cost_mb)

            fitting = [w for w in candidates if after(w) <= self._budget_mb]
            if not fitting and not busy:
                fitting = candidates[:1]  # one item always runs
            candidates = sorted(fitting, key=after)  # stable: idle workers first among equals
        return candidates[0] if candidates else None

    @staticmethod
    def _new_worker() -> _Worker:
        """A worker that replaces one: forked only while OpenCV is still not loaded here (_get_context)."""
        ctx = _get_context()
        if ctx.get_start_method() == "forkserver":
            _ensure_forkserver()  # started again, with the workers' environment, if it has died
        return _Worker(ctx)

    def _watch(self) -> None:
        """The pool's thread: take the workers' results, notice their ends, hand out the jobs left."""
        try:
            while True:
                with self._lock:
                    if self._closing:
                        return
                    owner = {}
                    for w in self._live:
                        owner[w.results] = owner[w.process.sentinel] = w
                ready = multiprocessing.connection.wait([*owner, self._wake_r])
                for handle in ready:
                    if handle == self._wake_r:
                        os.read(self._wake_r, 4096)
                    elif handle is owner[handle].results:
                        self._receive(owner[handle])
                    else:
                        self._drain(owner[handle])
                        self._ended(owner[handle])
                with self._lock:
                    self._dispatch()
                    self._changed.notify_all()
        except BaseException as exc:  # noqa: BLE001 - the consumer must not wait for results that cannot come
            with self._lock:
                self._error = exc
                self._changed.notify_all()

    def _receive(self, worker: _Worker) -> bool:
        """Take one result from `worker`; False when its pipe has ended (the worker has ended)."""
        try:
            job_id, ok, value = worker.results.recv()
        except (EOFError, OSError):
            self._ended(worker)
            return False
        with self._lock:
            if job_id in worker.queue:
                worker.queue.remove(job_id)
            worker.ran += 1
            self._done[job_id] = (ok, value)
        return True

    def _drain(self, worker: _Worker) -> None:
        """Take the results an ended worker sent before it ended."""
        while worker in self._live and worker.results.poll() and self._receive(worker):
            pass

    def _ended(self, worker: _Worker) -> None:
        """A worker has ended: its running job runs again alone in a fresh worker, or after a second death
        gets its `died` result; the job it held next goes back to the front of the line."""
        with self._lock:
            if worker not in self._live:
                return
            self._live.remove(worker)
        self._dead_cpu += process_cpu_seconds(worker.process.pid)  # before it is reaped
        worker.process.join()
        worker.close()
        why = describe_death(worker.process.exitcode)
        with self._lock:
            if self._closing or not worker.queue:
                return
            running, *held = worker.queue
            job = self._jobs[running]
            job.deaths += 1
            if job.deaths < 2:
                job.alone = True
                log.warning("the worker running %s died (%s); running it again on its own in a fresh worker",
                            _name(job), why)
                self._pending.appendleft(running)
            else:
                self._done[running] = (None, why)
            self._pending.extendleft(reversed(held))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        global _closed_workers_cpu
        if self._thread is None:
            return False
        # a last sample while the workers live: their memory only grows (startup.keep_freed_memory), so it holds their
        # peaks even when the sampler's thread, on a loaded machine, has not run since they started
        _tree.sample()
        with self._lock:
            self._closing = True
            workers, self._live = self._live, []
        os.write(self._wake_w, b".")
        self._thread.join()
        self._thread = None
        os.close(self._wake_r)
        os.close(self._wake_w)
        _pools.remove(self)
        if not _pools:
            _tree.stop()
        _closed_workers_cpu += self._dead_cpu + sum(process_cpu_seconds(w.process.pid) for w in workers)
        if exc[0] is not None:  # an error or Ctrl-C: the workers are gone before it propagates
            _end_pool(workers)
            return False
        # A drained pool ends in a thread while the caller goes on: ending the workers waits for the kernel to
        # free their memory (10-13 ms on templeSparseRing, while the next stage's set-up ran on one core).
        # A non-daemon thread: the interpreter's exit, or the next pool, waits for it.
        thread = threading.Thread(target=_end_pool, args=(workers,), name="end-worker-pool")
        thread.start()
        _ending.append(thread)
        return False


def _name(job: _Job) -> str:
    return job.name(job.item) if job.name is not None else "an item"


def _end_pool(workers: list[_Worker]) -> None:
    for w in workers:
        w.process.terminate()
    for w in workers:
        w.process.join()
        w.close()


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
def blas_threads(n: int) -> Iterator[None]:
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
