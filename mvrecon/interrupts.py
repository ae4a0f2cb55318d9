"""Ctrl-C (and SIGTERM) held back while compiled libraries initialise, so that it still ends the run cleanly.

A KeyboardInterrupt raised inside a compiled module's initialisation goes wrong after the fact: Open3D counts
its C++ allocations and, at process exit, finds them unbalanced, prints a page of memory statistics and calls
exit(1) over our 130; a Cython module registering its types with `abc` (scipy's, imported when skimage.data
first reads a photo) swallows it, and the scene is rendered to the end as if no Ctrl-C had come. These steps
take well under a second, so the Ctrl-C is held back until they are done, then passed on. The same goes for a
database unit (pycolmap's transaction commits whatever its block wrote).

SIGTERM (`timeout`, `kill`, a batch scheduler, `docker stop`) stops a run as Ctrl-C does: pycolmap installs glog's
failure handler for it on import, which printed a 30-line C stack dump, as if mvrecon had crashed; the CLI's
handler is put back after that import (`keep_handlers_after_import`).
"""

import importlib.util
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType

STOPPING = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def ctrl_c_deferred() -> Iterator[None]:
    """Run the block with SIGINT and SIGTERM recorded only; after it, deliver the first to its previous handler
    (the CLI's)."""
    # only the main thread handles signals; None: a handler Python did not install, which it cannot restore
    if threading.current_thread() is not threading.main_thread() or any(signal.getsignal(s) is None
                                                                        for s in STOPPING):
        yield
        return
    caught = []
    previous = {s: signal.signal(s, lambda signum, frame: caught.append(signum)) for s in STOPPING}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        if caught:
            signal.raise_signal(caught[0])


class _HandlersBack:
    """A finder on `sys.meta_path` that puts the Python signal handlers back after `module` is imported (its C
    code replaced them). Not an importlib.abc.MetaPathFinder: importing that took 7 ms of every start-up."""

    def __init__(self, module: str):
        self.module = module

    def find_spec(self, name, path=None, target=None):
        if name != self.module:
            return None
        sys.meta_path.remove(self)  # found once, by the other finders; the import happens once
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            handlers = {s: signal.getsignal(s) for s in STOPPING}
            try:
                run(module)
            finally:
                if threading.current_thread() is threading.main_thread():
                    for s, handler in handlers.items():
                        if callable(handler):
                            signal.signal(s, handler)

        spec.loader.exec_module = exec_module
        return spec


def keep_handlers_after_import(module: str = "pycolmap") -> None:
    """Have `module`'s first import leave this process's Python SIGINT/SIGTERM handlers in place."""
    if module not in sys.modules and not any(isinstance(f, _HandlersBack) and f.module == module
                                             for f in sys.meta_path):
        sys.meta_path.insert(0, _HandlersBack(module))


def import_open3d() -> ModuleType:
    """The open3d module; its first import runs with Ctrl-C held back."""
    with ctrl_c_deferred():
        import open3d  # noqa: PLC0415 - heavy, for the point-cloud readers only, with Ctrl-C held back
    return open3d
