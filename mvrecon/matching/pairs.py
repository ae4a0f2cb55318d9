"""Which image pairs to match: all of them, a sliding window over the sorted names (video), the most similar
images (unordered photo sets), or a pairs file.

A spec string selects the strategy: `exhaustive`, `sequential:K` (each image with the next K images in name
order), `retrieval:K` (each image with the K images nearest by a global descriptor, see `retrieval`) or the path
of a text file with one `name1 name2` pair per line (COLMAP's match-list format; `#` starts a comment). Pairs
come back as (name1, name2) in a stable order with no duplicates and no self-pairs.
"""

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InputError
from .retrieval import retrieval_pairs

log = logging.getLogger(__name__)

# strategies with a count, and how the count is named in a refusal
_COUNTED = {"sequential": "the window", "retrieval": "the number of nearest images"}


def exhaustive_pairs(names: list[str]) -> list[tuple[str, str]]:
    return [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]


def sequential_pairs(names: list[str], window: int) -> list[tuple[str, str]]:
    """Each image with the next `window` images (names sorted: frame order for video)."""
    names = sorted(names)
    return [(a, names[j]) for i, a in enumerate(names) for j in range(i + 1, min(len(names), i + 1 + window))]


def pairs_from_file(path: Path | str, names: list[str]) -> list[tuple[str, str]]:
    """Read `name1 name2` lines; unknown names, an image paired with itself and malformed lines are InputErrors
    naming file and line."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise InputError(f"{path}: cannot read pairs file ({exc.strerror or exc})") from None
    known = set(names)
    seen, out = set(), []
    for number, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = text.split()
        if len(parts) != 2:
            raise InputError(f"{path}:{number}: expected two image names, got {text!r}")
        for name in parts:
            if name not in known:
                raise InputError(f"{path}:{number}: unknown image {name!r}")
        if parts[0] == parts[1]:  # matching an image with itself makes no pair: a slip the user should see
            raise InputError(f"{path}:{number}: pairs image {parts[0]!r} with itself")
        key = tuple(sorted(parts))
        if key not in seen:
            seen.add(key)
            out.append((parts[0], parts[1]))
    return out


def check_spec(spec: str, where: str | None = None) -> str:
    """Validate a --pairs value early (before any work); returns it unchanged. `where`: how the user gave it, for
    the message (a --config file's key, say); the flag by default."""
    where = where or f"--pairs {spec}"
    if spec == "exhaustive" or Path(spec).is_file():
        return spec
    kind, colon, value = spec.partition(":")
    if kind in _COUNTED and colon:
        if value.isascii() and value.isdigit() and int(value) > 0:
            return spec
        raise InputError(f"{where}: {_COUNTED[kind]} must be a positive integer, e.g. {kind}:10")
    raise InputError(f"{where}: expected exhaustive, sequential:K, retrieval:K or an existing pairs file")


def select_pairs(spec: str, names: list[str],
                 descriptors: Callable[[str], np.ndarray] | None = None) -> list[tuple[str, str]]:
    """Pairs for a spec string (see module doc). `descriptors(name)`: an image's (n,d) descriptors, which
    `retrieval:K` needs (it reads each image's twice)."""
    check_spec(spec)
    if spec == "exhaustive":
        return exhaustive_pairs(sorted(names))
    if Path(spec).is_file():
        return pairs_from_file(spec, names)
    kind, _, value = spec.partition(":")
    if kind == "sequential":
        return sequential_pairs(names, int(value))
    k = int(value)
    if len(names) <= k + 1:  # every image's k nearest are all the others: no descriptor need be read
        log.info("%s on %d images: each has at most %d others, so all %d pairs are matched", spec, len(names),
                 max(len(names) - 1, 0), len(names) * (len(names) - 1) // 2)
        return exhaustive_pairs(sorted(names))
    if descriptors is None:
        raise ValueError(f"{spec}: selecting pairs by retrieval needs the images' descriptors")
    return retrieval_pairs(names, descriptors, k)
