"""The system's zlib is loaded before pycolmap can take its place: imported first by `mvrecon/__init__.py`.

pycolmap 4.1 to 4.2.1 carries its own zlib (1.3.2) inside its extension `pycolmap/_core*.so`, with the functions
exported, and loads the system's `libz.so.1` (1.2.13 on Debian 12) through the libgfortran it bundles. When pycolmap
is the first to load `libz.so.1`, the dynamic linker resolves the library's calls to its own functions
(deflateReset, deflateEnd, inflate, ...) to the first definition in the group loaded with it: pycolmap's
(`LD_DEBUG=bindings` prints `binding file .../libz.so.1 to .../pycolmap/_core...so: normal symbol 'deflateEnd'`).
From then on every user of the system zlib in the process (Pillow's and OpenCV's PNG writers, Python's `zlib`)
runs 1.2.13's deflateInit2_ and 1.3.2's deflateReset on one stream, whose states are laid out differently, and
the process aborts with `free(): invalid pointer` in deflateEnd. No version pin helps: pycolmap 4.1.1, 4.2.0 and
4.2.1 all abort so (Pillow's wheels, 11.3 to 13.0, bring no zlib and use the system's); 4.0.4 (zlib 1.3.1) mixes
the two builds all the same, and does not abort only because that layout happens to fit.

A `libz.so.1` loaded before pycolmap (Python's own `zlib` module links it) resolves its calls in itself, whatever
is imported later, and pycolmap's zlib then serves pycolmap alone. So every process that imports mvrecon before
pycolmap is safe: the `mvrecon` command, `python -m mvrecon.cli`, scripts and notebooks that import mvrecon first,
and the worker processes. One that imported pycolmap first is broken already and cannot be mended from Python:
`TAKEN_OVER` says so, importing mvrecon warns, and `cli.main` runs its command in a fresh interpreter instead.
"""

import ctypes
import os
import sys
import warnings
import zlib  # noqa: F401  (loads the system's libz.so.1, before pycolmap can be imported through mvrecon)


def _load_order() -> list[str]:
    """The paths of the shared objects of this process in the order they were loaded (`dl_iterate_phdr`)."""
    class Info(ctypes.Structure):  # the first two fields of `struct dl_phdr_info`
        _fields_ = [("addr", ctypes.c_void_p), ("name", ctypes.c_char_p)]

    paths = []

    @ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(Info), ctypes.c_size_t, ctypes.c_void_p)
    def visit(info, size, data):
        paths.append(os.fsdecode(info.contents.name or b""))
        return 0

    ctypes.CDLL(None).dl_iterate_phdr(visit, None)
    return paths


def _pycolmap_took_zlib() -> bool:
    """Whether pycolmap's extension was loaded before the system's libz.so.1 and defines zlib's functions itself:
    then libz.so.1 resolved its own calls to pycolmap's copies (see the module's docstring)."""
    if "pycolmap" not in sys.modules or not sys.platform.startswith("linux"):
        return False
    try:
        order = _load_order()
        core = next(k for k, p in enumerate(order) if f"{os.sep}pycolmap{os.sep}_core" in p)
        libz = next(k for k, p in enumerate(order) if os.path.basename(p).startswith("libz.so"))
        if libz < core:
            return False
        own = ctypes.cast(ctypes.CDLL(order[core]).deflateEnd, ctypes.c_void_p).value
        system = ctypes.cast(ctypes.CDLL(order[libz]).deflateEnd, ctypes.c_void_p).value
    except (StopIteration, OSError, AttributeError):  # not loaded, or a pycolmap without a zlib of its own
        return False
    return own != system


TAKEN_OVER = _pycolmap_took_zlib()  # this process imported pycolmap before mvrecon, and its zlib is broken
if TAKEN_OVER:
    warnings.warn("pycolmap was imported before mvrecon, and its own zlib has taken the place of the system's in "
                  "this process: writing a PNG (Pillow, OpenCV) or zlib data here aborts the process (free(): "
                  "invalid pointer). Import mvrecon (or zlib) before pycolmap; meanwhile mvrecon.cli.main runs "
                  "each command in a fresh process.", RuntimeWarning, stacklevel=2)
