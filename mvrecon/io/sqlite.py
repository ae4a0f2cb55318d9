"""Read-only access to an SQLite file (a COLMAP database), shared by `database.py` and the exports in `io/`."""

import os
import sqlite3
from contextlib import closing
from pathlib import Path

from ..errors import InputError


def connect_readonly(path: Path | str) -> closing[sqlite3.Connection]:
    """A read-only sqlite3 connection to the database file `path`, closed on leaving the `with` block; the
    caller reads with SQL what pycolmap's reader skips or refuses."""
    path = Path(path).resolve()
    uri = path.as_uri() + "?mode=ro"
    if not os.access(path.parent, os.W_OK):
        # a WAL database is read through a shared-memory file made next to it; in a folder that cannot be
        # written (a read-only mount, another user's run) SQLite cannot make it, and nothing can change the file
        wal = Path(f"{path}-wal")
        if wal.is_file() and wal.stat().st_size > 0:
            raise InputError(f"{path}: its last changes are still in {wal.name}, and its folder cannot be written "
                             "to merge them; copy the folder to a writable place and run again")
        uri += "&immutable=1"
    return closing(sqlite3.connect(uri, uri=True))
