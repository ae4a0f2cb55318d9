"""Files written whole or not at all, and JSON state files read back.

An interrupted run must leave the old file or the new one, never part of one: a cut-off report.json, config.json,
scene.json, record or degraded image would be taken for a finished one by the next run, or refused as damaged.
"""

import json
import os
from pathlib import Path


def replace_whole(dst, write) -> None:
    """`write(tmp)` to a hidden name next to `dst` (the same suffix: image writers choose the format by it), then
    rename it to `dst`. Hidden, so a folder listed meanwhile (images, a study's cells) does not show it."""
    dst = Path(dst)
    tmp = dst.with_name(f".{dst.stem}.partial{dst.suffix}")
    try:
        write(tmp)
        os.replace(tmp, dst)
    finally:
        tmp.unlink(missing_ok=True)


def outermost_new_folder(path) -> Path | None:
    """The outermost folder that `Path(path).mkdir(parents=True)` would create (None when `path` exists): what a
    run that fails must remove to leave nothing behind."""
    top = Path(path)
    if top.exists():
        return None
    while not top.parent.exists() and top.parent != top:
        top = top.parent
    return top


def write_json(path, data, **dumps) -> None:
    """`data` as JSON text (json.dumps options in `dumps`) in `path`, whole or not at all."""
    replace_whole(path, lambda tmp: tmp.write_text(json.dumps(data, **dumps) + "\n"))


def read_json_object(path) -> dict | None:
    """The JSON object in `path`; None when the file is missing, unreadable, cut off or holds something else."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None
