"""Features, matching and the parts of a partitioned mapping on a Dask distributed cluster (`--cluster`), beside
the local process pool.

`open_cluster("local:N")` starts a `distributed.LocalCluster` of N worker processes (one thread each) whose
scheduler and workers listen on 127.0.0.1 only; `open_cluster("tcp://host:8786")` (or `tls://`) connects to a
running scheduler (`dask scheduler`, `dask worker`, dask-jobqueue). A scheduler that is not on this machine needs
`security`: a TLS file (`load_security`), or the word `none` to accept an unauthenticated cluster on a network
the user trusts; anyone who reaches an unauthenticated scheduler can run code on its workers.

`Cluster.map` keeps `WorkerPool.map`'s contract (results in the items' order, `died(item, why)` for an item Dask
gave up on; `per_task` items a task), so the features stage and the partitioned mapping use either;
`Cluster.unordered` yields results as they complete (the matching stage's batches of pairs). Dask runs again the
tasks of a worker that dies (up to `distributed.scheduler.allowed-failures` times); the client writes each result
once. Data submitted with `Cluster.keep` lives in the task graph, so a worker that dies holding it costs a
recomputation, not the run.
"""

import contextlib
import ipaddress
import itertools
import logging
import os
import re
import socket
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import InputError
from .startup import keep_freed_memory

if TYPE_CHECKING:
    import distributed
    from distributed.security import Security

log = logging.getLogger(__name__)

_LOCAL = re.compile(r"local:(\d+)")
_REMOTE = re.compile(r"(tcp|tls)://(\[[0-9a-fA-F:.]+\]|[^:/\s]+):(\d+)")
INSECURE = "none"  # --cluster-security value: an unauthenticated cluster on a trusted network, knowingly
# Security() keyword -> the keys a security file may use for it (TOML or YAML; dashes or underscores)
_SECURITY_KEYS = {"tls_ca_file": ("ca-file", "tls-ca-file"), "tls_client_cert": ("cert", "tls-client-cert"),
                  "tls_client_key": ("key", "tls-client-key")}
# Dask's settings for a `local:N` cluster: the periodic work of its scheduler, nannies and workers made rare.
# With Dask's defaults an idle LocalCluster of 2 workers used 0.16 of a core (the client's process 0.06: the
# event loops' health ticks every 20 ms and the nannies' memory checks every 100 ms; each worker 0.05, a third of
# it the statistical profiler sampling every 10 ms); with these 0.02. On a 2-core machine that is CPU the
# workers' SIFT and RANSAC need, and on a loaded machine it is paid for every second the run lasts.
QUIET_LOCAL_CLUSTER = {
    "distributed.worker.profile.enabled": False,  # the dashboard's profile, which a local:N run has no use for
    "distributed.admin.tick.interval": "1s",  # the check that an event loop is not blocked (a warning only)
    "distributed.admin.system-monitor.interval": "5s",  # the dashboard's CPU and network figures
    "distributed.worker.memory.monitor-interval": "500ms",  # the memory limits checked twice a second
    # worker processes forked from a forkserver that has imported Dask once, instead of spawned interpreters that
    # each import it afresh: a LocalCluster of 2 opened in 4.7-5.1 s instead of 7.1-7.7 s and closed in 0.2 s
    # instead of 2 s on a shared 2-core machine. The forkserver, multiprocessing's one (the process pool's too),
    # starts with one BLAS and OpenMP thread in its environment whichever of them starts it.
    "distributed.worker.multiprocessing-method": "forkserver",
}


class ClusterLost(InputError):
    """The scheduler or the connection to it was lost during a run, or workers kept dying on a task: what was
    written so far is kept."""


@dataclass(frozen=True)
class ClusterSpec:
    """Where the work goes: `local:N`, or a scheduler's `tcp://host:port` / `tls://host:port`; `security`: a TLS
    file, `none`, or empty (a local or loopback cluster)."""

    address: str
    security: str = ""

    @property
    def local_workers(self) -> int | None:
        """N of `local:N`, None for a scheduler's address."""
        m = _LOCAL.fullmatch(self.address)
        return int(m.group(1)) if m else None


def parse_cluster(address: str, security: str | None = None) -> ClusterSpec:
    """`--cluster` and `--cluster-security` checked before any work: InputError for a malformed address, a
    missing security file, or a scheduler off this machine without security."""
    security = security or ""
    m = _LOCAL.fullmatch(address)
    if m:
        if int(m.group(1)) < 1:
            raise InputError(f"--cluster {address}: a local cluster needs at least 1 worker")
        if security and security != INSECURE:
            load_security(security)
        return ClusterSpec(address, security)
    m = _REMOTE.fullmatch(address)
    if not m:
        raise InputError(f"--cluster {address}: expected local:N or a scheduler's tcp://HOST:PORT (or tls://)")
    if security and security != INSECURE:
        load_security(security)
    elif not security and not is_loopback(m.group(2).strip("[]")):
        raise InputError(f"--cluster {address}: a scheduler on another machine needs --cluster-security FILE "
                         f"(TLS certificates, see docs/distributed.md), or --cluster-security {INSECURE} to accept "
                         "an unauthenticated cluster on a network you trust")
    if m.group(1) == "tls" and (not security or security == INSECURE):
        raise InputError(f"--cluster {address}: a tls:// scheduler needs --cluster-security FILE")
    return ClusterSpec(address, security)


def is_loopback(host: str) -> bool:
    """Whether `host` (a name or an address) is this machine's loopback interface; a name that does not
    resolve is not."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None)
    except OSError:
        return False
    return bool(infos) and all(ipaddress.ip_address(info[4][0]).is_loopback for info in infos)


def load_security(path: Path | str) -> "Security":
    """A `distributed.security.Security` requiring encryption, from a TOML or YAML file naming the CA, the
    client's certificate and its key (`ca-file`, `cert`, `key`; paths relative to the file). InputError naming
    the file when it cannot be read, a key is unknown or missing, or a named file does not exist."""
    from distributed.security import Security  # noqa: PLC0415 - heavy, and only for --cluster

    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the cluster security file ({exc.strerror})") from None
    try:
        if path.suffix.lower() == ".toml":
            import tomllib  # noqa: PLC0415

            table = tomllib.loads(text)
        else:
            import yaml  # noqa: PLC0415 - Dask's own dependency

            table = yaml.safe_load(text)
    except Exception as exc:  # noqa: BLE001 - either parser's error, reported as the file's
        raise InputError(f"{path}: not a valid security file ({exc})") from None
    if not isinstance(table, dict):
        raise InputError(f"{path}: expected a table of ca-file, cert and key")
    names = {alias: key for key, aliases in _SECURITY_KEYS.items() for alias in (*aliases, key)}
    kwargs = {}
    for key, value in table.items():
        key = str(key).replace("_", "-")
        field = names.get(key) or names.get(key.replace("-", "_"))
        if field is None:
            raise InputError(f"{path}: unknown key {key!r} (known: ca-file, cert, key)")
        file = (path.parent / str(value)).resolve()
        if not file.is_file():
            raise InputError(f"{path}: {key} = {value}: no such file")
        kwargs[field] = str(file)
    missing = [_SECURITY_KEYS[k][0] for k in _SECURITY_KEYS if k not in kwargs]
    if missing:
        raise InputError(f"{path}: missing {', '.join(missing)}")
    return Security(require_encryption=True, **kwargs)


_worker_prepared = False  # in a worker process: whether `_on_prepared_worker` has prepared it


def _on_prepared_worker(func: Callable, *args):
    """`func(*args)` in a worker process prepared, once, as the process pool prepares its workers
    (executor.py): OpenCV on one thread, a worker thread per core being the parallelism, and the memory it frees
    kept for the next task (startup.keep_freed_memory), where Dask's workers would give the heap back from 64 KB
    (MALLOC_TRIM_THRESHOLD_) and SIFT's buffers would be mapped afresh for every image."""
    global _worker_prepared
    if not _worker_prepared:
        import cv2  # noqa: PLC0415 - in the worker, where the tasks need it anyway

        cv2.setNumThreads(1)
        keep_freed_memory(one_arena=True)
        _worker_prepared = True
    return func(*args)


class Cluster:
    """A connected Dask cluster: its client, and the LocalCluster started for it (`local:N`), closed with it.

    `sent_bytes` / `received_bytes`: what this client sent with its tasks and received as results (dask's
    sizeof), for the benchmark."""

    def __init__(self, client: "distributed.Client", spec: ClusterSpec,
                 local: "distributed.LocalCluster | None" = None):
        self.client, self.spec, self._local = client, spec, local
        self.sent_bytes = self.received_bytes = 0
        self.tasks = 0

    @property
    def workers(self) -> int:
        """The worker threads of the cluster now (at least 1: a cluster whose workers are still starting)."""
        return max(1, sum(self._call(self.client.nthreads).values()))

    def __repr__(self) -> str:
        return f"Cluster({self.spec.address}, {self.workers} worker threads)"

    def worker_pids(self) -> dict[str, int]:
        """Worker address -> process id (the workers on this machine, or anywhere: for tests and tools)."""
        return self.client.run(os.getpid)

    def workers_see(self, folder: Path | str) -> bool:
        """Whether every worker sees `folder` at the same path (a shared file system, or this machine); asked
        once a worker has joined (a cluster whose workers are still starting is waited for)."""
        if not self.client.nthreads():
            log.info("cluster %s: waiting for its first worker", self.spec.address)
            self._call(lambda: self.client.wait_for_workers(1))
        seen = self._call(lambda: self.client.run(os.path.isdir, str(Path(folder).resolve())))
        return bool(seen) and all(seen.values())

    def peer_bytes(self) -> int:
        """Bytes the workers have sent to one another so far (the data a task needed from another worker)."""
        def outgoing(dask_worker) -> int:
            return int(getattr(dask_worker, "transfer_outgoing_bytes_total", 0))
        return sum(self._call(lambda: self.client.run(outgoing)).values())

    def keep(self, func: Callable, *args, key: str) -> "distributed.Future":
        """A future of `func(*args)`, computed on a worker and kept there (and copied to the workers whose tasks
        need it) until `release`. Submitted as a task, not scattered: a worker that dies holding it costs its
        recomputation from the task, where scattered data would be lost with the tasks that need it."""
        self._count_sent(args)
        return self._call(lambda: self.client.submit(_on_prepared_worker, func, *args, key=key, pure=False))

    def release(self, futures: Iterable) -> None:
        """Let the cluster forget the data of `futures` (from `keep`)."""
        for future in futures:
            future.release()

    def map(self, func: Callable, items: Iterable, *, name: Callable | None = None, cost: Callable | None = None,
            died: Callable | None = None, window: int | None = None, per_task: int = 1) -> Iterator:
        """`func(item)` for every item, in the items' order, as `WorkerPool.map` (`cost` is left to Dask's own
        memory management); `per_task` items a task (`_Each`), at most `window` tasks in flight (default:
        `_window`), handed out and fetched a few at a time (`_submit`, `_results`)."""
        del cost
        if per_task > 1:
            def died_all(batch, why):
                return [died(item, why) for item in batch]

            for results in self.map(_Each(func), _batches(items, per_task), window=window,
                                    name=None if name is None else lambda batch: ", ".join(map(name, batch)),
                                    died=None if died is None else died_all):
                yield from results
            return
        from distributed import KilledWorker, wait  # noqa: PLC0415

        items = iter(items)
        window = window or self._window()
        chunk = self._chunk(window)
        in_flight = deque()  # (item, future), in the items' order

        def died_result(item, exc):
            why = f"Dask gave it up after workers died running it ({exc})"
            if died is None:
                raise exc
            log.warning("%s: %s", name(item) if name else "an item", why)
            return died(item, why)

        try:
            in_flight.extend(self._submit(func, items, window))
            while in_flight:
                self._call(lambda: wait([in_flight[0][1]]))
                ready = [in_flight.popleft()]
                while in_flight and in_flight[0][1].done():
                    ready.append(in_flight.popleft())
                for (item, _), result in zip(ready, self._results([f for _, f in ready], KilledWorker)):
                    yield died_result(item, result) if isinstance(result, KilledWorker) else result
                if window - len(in_flight) >= chunk:
                    in_flight.extend(self._submit(func, items, window - len(in_flight)))
        finally:
            for _, future in in_flight:
                future.cancel()

    def unordered(self, func: Callable, items: Iterable, *, window: int | None = None) -> Iterator[tuple]:
        """(item, `func(item)`) for every item, as they complete; at most `window` items in flight (default:
        `_window`), handed out and fetched a few at a time. An exception `func` raised is raised here; a task Dask
        gave up on after its workers died (`distributed.scheduler.allowed-failures`) raises ClusterLost."""
        from distributed import KilledWorker, wait  # noqa: PLC0415

        items = iter(items)
        window = window or self._window()
        chunk = self._chunk(window)
        in_flight = {}  # future -> item

        try:
            in_flight.update((f, item) for item, f in self._submit(func, items, window))
            while in_flight:
                done = self._call(lambda: wait(list(in_flight), return_when="FIRST_COMPLETED")).done
                ready = [f for f in in_flight if f in done]  # in the order handed out
                for future, result in zip(ready, self._results(ready, KilledWorker)):
                    item = in_flight.pop(future)
                    if isinstance(result, KilledWorker):
                        raise ClusterLost(f"--cluster {self.spec.address}: Dask gave a task up after the workers "
                                          f"running it died ({_one_line(result)}); the work written so far is "
                                          "kept: rerun the same command to continue") from None
                    yield item, result
                if window - len(in_flight) >= chunk:
                    in_flight.update((f, item) for item, f in self._submit(func, items, window - len(in_flight)))
        finally:
            for future in in_flight:
                future.cancel()

    def _window(self) -> int:
        """Tasks in flight by default: four per worker thread, and two, so that a worker has its next tasks
        while the client takes the results of the last ones."""
        return 4 * self.workers + 2

    def _chunk(self, window: int) -> int:
        """Tasks handed out in one go: half the window (at least a task per worker thread)."""
        return min(window, max(self.workers, window // 2))

    def _submit(self, func: Callable, items: Iterator, count: int) -> list[tuple]:
        """[(item, future)] of `func(item)` for the next `count` items, handed to the scheduler in one message,
        each a task on a prepared worker (`_on_prepared_worker`) whose key names `func`, as Dask's own keys do (the
        task stream, the benchmark's stages); their bytes counted as sent. A message per task cost the client
        (and a LocalCluster's scheduler, in the same process) about twice the CPU per task."""
        batch = list(itertools.islice(items, count))
        if not batch:
            return []
        self._count_sent(batch)
        keys = [f"{func.__name__}-{uuid.uuid4().hex}" for _ in batch]
        futures = self._call(lambda: self.client.map(_on_prepared_worker, [func] * len(batch), batch, key=keys,
                                                     pure=False))
        return list(zip(batch, futures))

    def _results(self, futures: list, killed: type) -> list:
        """The results of finished `futures`, fetched in one go; when that fails, one by one, so that each
        future's own error is raised, and a task Dask gave up on (`killed`, KilledWorker) is returned as its
        exception."""
        try:
            results = self._call(lambda: self.client.gather(futures))
        except ClusterLost:
            raise
        except Exception:  # noqa: BLE001 - one of them failed: each is asked on its own below
            results = []
            for future in futures:
                try:
                    results.append(self._call(future.result))
                except killed as exc:
                    results.append(exc)
        for result in results:
            if not isinstance(result, killed):
                self._count_received(result)
        self.tasks += len(results)
        return results

    def _count_sent(self, obj) -> None:
        from dask.sizeof import sizeof  # noqa: PLC0415

        self.sent_bytes += sizeof(obj)

    def _count_received(self, obj) -> None:
        from dask.sizeof import sizeof  # noqa: PLC0415

        self.received_bytes += sizeof(obj)

    def _call(self, func: Callable):
        """`func()`, a lost scheduler raised as ClusterLost (a one-line error, the work written kept)."""
        from distributed import CancelledError  # noqa: PLC0415
        from distributed.comm import CommClosedError  # noqa: PLC0415

        try:
            return func()
        except (CommClosedError, CancelledError) as exc:
            raise ClusterLost(f"--cluster {self.spec.address}: the connection to the scheduler was lost "
                              f"({type(exc).__name__}: {_one_line(exc)}); the work written so far is kept: rerun the "
                              "same command (reconstruct with --resume) to continue") from None


class _Each:
    """A task of several items: `func` over each, in their order. A task costs the client and a LocalCluster's
    scheduler about 25 ms of CPU whatever it does (on a shared 2-core machine), paid once for them all. Named as
    `func`, for the task's key."""

    def __init__(self, func: Callable):
        self.func, self.__name__ = func, func.__name__

    def __call__(self, items: list) -> list:
        return [self.func(item) for item in items]


def _batches(items: Iterable, size: int) -> Iterator[list]:
    items = iter(items)
    while batch := list(itertools.islice(items, size)):
        yield batch


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


@contextmanager
def open_cluster(spec: ClusterSpec, *, connect_timeout: float = 30.0) -> Iterator[Cluster]:
    """The cluster of `spec`, connected for the block: a LocalCluster of N single-threaded worker processes on
    127.0.0.1 (no dashboard) for `local:N`, closed at the block's end; else a client of the scheduler at
    `spec.address` (InputError when it cannot be reached within `connect_timeout` seconds)."""
    import dask  # noqa: PLC0415 - heavy (~2 s), and only for --cluster
    import distributed  # noqa: PLC0415

    if not log.isEnabledFor(logging.DEBUG):  # Dask's news of workers coming and going, unless -v -v
        logging.getLogger("distributed").setLevel(logging.WARNING)
        # the tracebacks of a lost scheduler's reconnection: ClusterLost says it in one line
        for name in ("distributed.client", "distributed.utils"):
            logging.getLogger(name).setLevel(logging.CRITICAL)
    start = time.perf_counter()
    security = None
    if spec.security and spec.security != INSECURE:
        security = load_security(spec.security)
    local = None
    n = spec.local_workers
    # set for the block: a worker the nanny starts again after a death takes the settings the nanny was given
    with dask.config.set(QUIET_LOCAL_CLUSTER) if n is not None else contextlib.nullcontext():
        try:
            if n is not None:
                local = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                 host="127.0.0.1", dashboard_address=None,
                                                 silence_logs=logging.WARNING)
                client = distributed.Client(local)
            else:
                client = distributed.Client(spec.address, security=security, timeout=connect_timeout)
        except (OSError, TimeoutError) as exc:
            if local is not None:
                local.close()
            raise InputError(f"--cluster {spec.address}: cannot reach the scheduler ({exc})") from None
        try:
            cluster = Cluster(client, spec, local)
            log.info("cluster %s: %d worker threads, connected in %.1f s", spec.address, cluster.workers,
                     time.perf_counter() - start)
            yield cluster
        finally:
            client.close()
            if local is not None:  # its workers have nothing left to save: a slow one is ended without a warning
                logging.getLogger("distributed.nanny").setLevel(logging.ERROR)
                local.close()
