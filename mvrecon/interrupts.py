"""Ctrl-C held back while compiled libraries initialise, so that it still ends the run with exit code 130.

A KeyboardInterrupt raised inside a compiled module's initialisation goes wrong after the fact: Open3D counts
its C++ allocations and, at process exit, finds them unbalanced, prints a page of memory statistics and calls
exit(1) over our 130; a Cython module registering its types with `abc` (scipy's, imported when skimage.data
first reads a photo) swallows it, and the scene is rendered to the end as if no Ctrl-C had come. These steps
take well under a second, so the Ctrl-C is held back until they are done, then passed on.
"""

import signal
import threading
from contextlib import contextmanager


@contextmanager
def ctrl_c_deferred():
    """Run the block with SIGINT recorded only; after it, deliver one to the previous handler (the CLI's)."""
    # only the main thread handles signals; None: a handler Python did not install, which it cannot restore
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is None:
        yield
        return
    caught = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            signal.raise_signal(signal.SIGINT)


def import_open3d():
    """The open3d module; its first import runs with Ctrl-C held back."""
    with ctrl_c_deferred():
        import open3d
    return open3d
