"""Files written whole or not at all, and JSON state files read back.

An interrupted run must leave the old file or the new one, never part of one: a cut-off report.json, config.json,
scene.json, record or degraded image would be taken for a finished one by the next run, or refused as damaged.
"""

import codecs
import fcntl
import json
import os
import shutil
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import DiskFull, InputError

_held: dict[Path, int] = {}  # folder -> how many nested `hold_folder` blocks of this process hold it
_made: dict[Path, Path] = {}  # folder held -> the outermost folder its `hold_folder` created


def replace_whole(dst: Path | str, write: Callable[[Path], object]) -> None:
    """`write(tmp)` to a hidden name next to `dst` (the same suffix: image writers choose the format by it), then
    rename it to `dst`. Hidden, so a folder listed meanwhile (images, a study's cells) does not show it."""
    dst = Path(dst)
    tmp = dst.with_name(f".{dst.stem}.partial{dst.suffix}")
    try:
        write(tmp)
        os.replace(tmp, dst)
    finally:
        tmp.unlink(missing_ok=True)


def require_room(path: Path | str, nbytes: int, spare: int = 32 << 20) -> None:
    """Refuse, naming `path`, to write `nbytes` where the disk has less than that and `spare` free. For writers
    that cannot report a full disk themselves: pycolmap aborts the process when a database commit or an image
    of its undistorter fails to be written."""
    folder = Path(path)
    while not folder.is_dir() and folder != folder.parent:  # the nearest folder that exists
        folder = folder.parent
    stat = os.statvfs(folder)
    free, wanted = stat.f_bavail * stat.f_frsize, int(nbytes) + spare
    if free < wanted:
        raise DiskFull(f"{path}: the disk is full ({free / 2**20:.1f} MB free, {wanted / 2**20:.0f} MB wanted to "
                       f"write on); {DiskFull.advice}")


def outermost_new_folder(path: Path | str) -> Path | None:
    """The outermost folder that `Path(path).mkdir(parents=True)` would create (None when `path` exists, unless
    this run's `hold_folder` made it): what a run that fails must remove to leave nothing behind."""
    top = Path(path)
    if top.exists():  # made by the `hold_folder` this run is inside, or there before the run
        return _made.get(top.resolve())
    while not top.parent.exists() and top.parent != top:
        top = top.parent
    return top


@contextmanager
def made_folder(path: Path | str,
                removed_on: type[BaseException] | tuple[type[BaseException], ...] = BaseException,
                within: Path | str | None = None) -> Iterator[Path]:
    """Create folder `path` (with its parents) for the block; when the block raises one of `removed_on`, remove
    what this run created, so a refused or failed run leaves no folder behind, and an existing folder (the user's,
    or an earlier run's) stays. `within`: the path whose new folders count (default `path`; a run that keeps
    resumable work in OUT/.stages removes only that when OUT already existed)."""
    created = outermost_new_folder(path if within is None else within)
    Path(path).mkdir(parents=True, exist_ok=True)
    try:
        yield Path(path)
    except removed_on:
        if created is not None:
            shutil.rmtree(created, ignore_errors=True)
        raise


@contextmanager
def hold_folder(path: Path | str) -> Iterator[Path]:
    """Hold output folder `path` for the block, against another mvrecon process: two runs writing one database
    broke the second with a SQLite constraint error, and two compares into one folder each broke the other's runs.
    An exclusive `flock` on the folder itself (no lock file is left behind), which the kernel releases when the
    process ends, however it ends; nested blocks of one process share it. A missing folder is created first (so
    that a second run started meanwhile is refused too) and removed afterwards if the block left it empty. A path
    that cannot be a folder is left to the command to report."""
    path = Path(path)
    created = outermost_new_folder(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        key = path.resolve()
    except OSError:  # a file in the way, no rights: the command's own checks say so
        key = None
    if key is None:
        yield path
        return
    fd = None
    if key in _held:  # an enclosing block of this process holds it (and owns what was created)
        created = None
    else:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise InputError(f"{path}: another mvrecon run is using this folder; wait for it to end, or choose "
                             "another folder") from None
        except OSError:  # a file system without locks (some network or FUSE mounts): run unguarded
            pass
    _held[key] = _held.get(key, 0) + 1
    if created is not None:
        _made[key] = created
    try:
        yield path
    finally:
        _held[key] -= 1
        if not _held[key]:
            del _held[key]
        if fd is not None:
            os.close(fd)  # closing the only descriptor releases the lock
        if created is not None:  # what this call made, if the block left it empty (or removed it)
            del _made[key]
            for folder in (path, *path.parents):
                try:
                    if folder.exists():
                        folder.rmdir()
                except OSError:
                    break
                if folder == created:
                    break


def _escape_undecodable(exc):
    """Codec error handler: a file name's bytes that are not UTF-8 (kept by Python as surrogates) as \\xNN."""
    if not isinstance(exc, UnicodeEncodeError):
        raise exc
    text = exc.object[exc.start:exc.end]
    return "".join(f"\\x{ord(c) - 0xDC00:02x}" if 0xDC80 <= ord(c) <= 0xDCFF else f"\\u{ord(c):04x}"
                   for c in text), exc.end


ESCAPE = "mvrecon-escape"  # the handler's name, for streams that print file names (the CLI's stdout and stderr)
codecs.register_error(ESCAPE, _escape_undecodable)


def printable_name(name: str) -> str:
    """`name` (or any text holding file names) with the bytes that are not UTF-8 (which Python keeps as
    surrogates) written as \\xNN escapes."""
    return name.encode("utf-8", ESCAPE).decode("utf-8")


def some_names(names: Iterable[str], shown: int = 1) -> str:
    """The first `shown` of `names` and how many more, for a message that names a few files."""
    names = list(names)
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def write_json(path: Path | str, data: object, **dumps: object) -> None:
    """`data` as JSON text (json.dumps options in `dumps`) in `path`, whole or not at all."""
    replace_whole(path, lambda tmp: tmp.write_text(json.dumps(data, **dumps) + "\n"))


def read_json_object(path: Path | str) -> dict | None:
    """The JSON object in `path`; None when the file is missing, unreadable, cut off or holds something else."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None
