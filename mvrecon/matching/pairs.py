"""Which image pairs to match: all of them, a sliding window over the sorted names (video), the nearest by GPS
position (aerial surveys), the most similar images (unordered photo sets), or a pairs file; `auto` chooses.

A spec string selects the strategy:
- `exhaustive`: every pair, n(n-1)/2 of them;
- `sequential:K`: each image with the next K in name order, plus loop detection: every `LOOP_EVERY`-th frame
  with its `LOOP_NEAREST` most similar frames (by retrieval) outside its window, so that a video that comes back
  to where it started is closed;
- `spatial:K` or `spatial:K:R`: each image with its K nearest by GPS EXIF position (metres, east/north/up),
  only those within R metres if R is given; images without a position fall back to their K nearest by retrieval;
- `retrieval:K`: each image with the K images nearest by a global descriptor (see `retrieval`);
- `A+B`: the union of two (or more) of the above, e.g. `sequential:10+retrieval:5`;
- `auto` (the default): `exhaustive` below `AUTO_EXHAUSTIVE` images (the same pairs as exhaustive matching),
  otherwise chosen from what the images offer (`choose_auto`), and logged with its reason;
- the path of a text file with one `name1 name2` pair per line (COLMAP's match-list format; `#` starts a comment).
Pairs come back as (name1, name2) in a stable order with no duplicates and no self-pairs. All but `exhaustive`
select O(n K) pairs.
"""

import logging
import re
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.gps import to_enu
from .retrieval import GlobalVectors, global_vectors, nearest, ranking, retrieval_pairs, similarities

log = logging.getLogger(__name__)

# strategies with a count, and how the count is named in a refusal
_COUNTED = {"sequential": "the window", "retrieval": "the number of nearest images",
            "spatial": "the number of nearest images"}
_EXPECTED = "expected auto, exhaustive, sequential:K, spatial:K[:R], retrieval:K, A+B or an existing pairs file"

LOOP_EVERY = 2  # every 2nd frame of `sequential:K` looks for a loop closure ...
LOOP_NEAREST = 5  # ... among its 5 most similar frames outside its window
# (on street_long, 100 frames round a block: 72 pairs farther than 50 frames apart, 20% of the overlapping ones,
# where every 5th frame found 30 and 8.8%; 12% more pairs in all)

# `auto`: below this many images every pair is matched (see docs/benchmarks.md, "Pair selection")
AUTO_EXHAUSTIVE = 50
AUTO_GPS_SHARE = 0.8  # images with a GPS position for `auto` to pair by position
AUTO_VIDEO_SHARE = 0.9  # names in one numbered sequence for `auto` to treat the images as video frames
AUTO_VIDEO_AGREE = 0.6  # ... and images whose most similar image is within the window
# on aerial_survey (100 views, every 5th oblique) this kept 94% of the ground-truth overlapping pairs in 1,397 of
# 4,950; spatial:20 alone 88.5%, spatial:20+retrieval:10 89.2% (docs/benchmarks.md, "Pair selection")
AUTO_SPATIAL = "spatial:20+retrieval:20"
AUTO_SEQUENTIAL_K = 10
AUTO_RETRIEVAL = "retrieval:20"

Positions = Callable[[str], tuple[float, float, float] | None]  # an image's GPS (lat, lon, alt) or None


@dataclass(frozen=True)
class PairPlan:
    """The pairs selected, the strategy that selected them (`auto` resolved) and why it was chosen."""

    spec: str
    reason: str
    pairs: list[tuple[str, str]]


def exhaustive_pairs(names: list[str]) -> list[tuple[str, str]]:
    return [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]


def window_pairs(names: list[str], window: int) -> list[tuple[str, str]]:
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


def _positive_int(text: str) -> bool:
    return text.isascii() and text.isdigit() and int(text) > 0


def _positive_number(text: str) -> bool:
    try:
        value = float(text)
    except ValueError:
        return False
    return text.isascii() and np.isfinite(value) and value > 0


def check_spec(spec: str, where: str | None = None) -> str:
    """Validate a --pairs value early (before any work); returns it unchanged. `where`: how the user gave it, for
    the message (a --config file's key, say); the flag by default."""
    where = where or f"--pairs {spec}"
    if spec in ("auto", "exhaustive") or Path(spec).is_file():
        return spec
    for part in spec.split("+"):
        kind, colon, value = part.partition(":")
        if kind not in _COUNTED or not colon:
            raise InputError(f"{where}: {_EXPECTED}")
        count, _, radius = value.partition(":") if kind == "spatial" else (value, "", "")
        if not _positive_int(count):
            raise InputError(f"{where}: {_COUNTED[kind]} must be a positive integer, e.g. {kind}:10")
        if kind == "spatial" and value.count(":") and not _positive_number(radius):
            raise InputError(f"{where}: the radius must be a positive number of metres, e.g. spatial:10:50")
    return spec


class _Vectors:
    """The images' `global_vectors`, made on first use and then shared by every part of a spec."""

    def __init__(self, names: list[str], descriptors: Callable[[str], np.ndarray] | None):
        self.names, self.descriptors, self._vectors = names, descriptors, None

    def get(self, spec: str) -> GlobalVectors:
        if self._vectors is None:
            if self.descriptors is None:
                raise ValueError(f"{spec}: selecting pairs by retrieval needs the images' descriptors")
            self._vectors = global_vectors(self.names, self.descriptors)
        return self._vectors


def select_pairs(spec: str, names: list[str], descriptors: Callable[[str], np.ndarray] | None = None,
                 positions: Positions | None = None) -> list[tuple[str, str]]:
    """Pairs for a spec string (see module doc); `plan_pairs(...).pairs`."""
    return plan_pairs(spec, names, descriptors, positions).pairs


def plan_pairs(spec: str, names: list[str], descriptors: Callable[[str], np.ndarray] | None = None,
               positions: Positions | None = None) -> PairPlan:
    """The pairs of a spec string and the strategy that chose them. `descriptors(name)`: an image's (n,d)
    descriptors, which retrieval, loop detection and `auto` need (each image's are read twice);
    `positions(name)`: its GPS position or None, which `spatial` and `auto` need (each image's read once)."""
    check_spec(spec)
    names = sorted(names)
    vectors = _Vectors(names, descriptors)
    positions = cache(positions) if positions is not None else None  # `auto` and `spatial` both ask: one read
    reason = "given"
    if spec == "auto":
        spec, reason = choose_auto(names, vectors, positions)
        log.info("pairs auto: %s (%s)", spec, reason)
    if spec == "exhaustive":
        return PairPlan(spec, reason, exhaustive_pairs(names))
    if Path(spec).is_file():
        return PairPlan(spec, reason, pairs_from_file(spec, names))
    found = set()
    for part in spec.split("+"):
        found.update(_part_pairs(part, names, vectors, positions))
    order = {name: i for i, name in enumerate(names)}
    return PairPlan(spec, reason, sorted(found, key=lambda p: (order[p[0]], order[p[1]])))


def _part_pairs(part: str, names: list[str], vectors: _Vectors,
                positions: Positions | None) -> list[tuple[str, str]]:
    kind, _, value = part.partition(":")
    count, _, radius = value.partition(":")
    k = int(count)
    if kind == "sequential":
        return sequential_pairs(names, k, vectors)
    if len(names) <= k + 1 and kind == "retrieval":  # every image's k nearest are all the others
        log.info("%s on %d images: each has at most %d others, so all %d pairs are matched", part, len(names),
                 max(len(names) - 1, 0), len(names) * (len(names) - 1) // 2)
        return exhaustive_pairs(names)
    if kind == "retrieval":
        return retrieval_pairs(names, vectors.descriptors, k, vectors=vectors.get(part))
    if positions is None:
        raise ValueError(f"{part}: selecting pairs by position needs the images' GPS positions")
    return spatial_pairs(names, [positions(n) for n in names], k, float(radius) if radius else None, vectors)


def sequential_pairs(names: list[str], window: int, vectors: _Vectors | None = None) -> list[tuple[str, str]]:
    """`window_pairs` plus loop detection: every `LOOP_EVERY`-th frame with its `LOOP_NEAREST` most similar
    frames farther than `window` in the sequence (needs `vectors` when there are such frames)."""
    names = sorted(names)
    pairs = set(window_pairs(names, window))
    n = len(names)
    if n > window + 1:
        if vectors is None:
            raise ValueError(f"sequential:{window}: loop detection needs the images' descriptors")
        g = vectors.get(f"sequential:{window}")
        found = g.found
        if len(found) > window + 1:
            expanded, raw = ranking(g.vectors[found])
            frame = np.asarray(found)
            near = np.abs(frame[:, None] - frame[None, :]) <= window
            expanded[near], raw[near] = -np.inf, -np.inf
            queries = [r for r, i in enumerate(found) if i % LOOP_EVERY == 0]
            best = nearest(expanded[queries], LOOP_NEAREST, tiebreak=raw[queries])
            loops = {tuple(sorted((found[q], found[int(j)]))) for q, row in zip(queries, best) for j in row
                     if np.isfinite(expanded[q, j])}
            log.debug("sequential:%d: %d loop-closure pairs from %d frames", window, len(loops), len(queries))
            pairs |= {(names[i], names[j]) for i, j in loops}
    return sorted(pairs)


def spatial_pairs(names: list[str], gps: list, k: int, radius: float | None,
                  vectors: _Vectors | None = None) -> list[tuple[str, str]]:
    """Each image with its k nearest (within `radius` metres if given) by GPS position `gps[i]` (lat, lon, alt
    or None); an image without one is paired with its k nearest by retrieval (needs `vectors`)."""
    has = [i for i, p in enumerate(gps) if p is not None]
    pairs = set()
    if len(has) > 1:
        enu = to_enu(np.array([gps[i] for i in has], float))
        dist = np.linalg.norm(enu[:, None, :] - enu[None, :, :], axis=2)
        np.fill_diagonal(dist, np.inf)
        if radius is not None:
            dist[dist > radius] = np.inf
        order = np.argsort(dist, axis=1, kind="stable")[:, :k]
        pairs = {tuple(sorted((has[a], has[int(b)]))) for a, row in enumerate(order) for b in row
                 if np.isfinite(dist[a, b])}
    missing = [i for i, p in enumerate(gps) if p is None]
    if missing and len(names) > 1:
        log.info("spatial:%d: %d of %d images have no GPS position: paired by retrieval", k, len(missing),
                 len(names))
        if vectors is None:
            raise ValueError(f"spatial:{k}: images without GPS need the images' descriptors")
        g = vectors.get(f"spatial:{k}")
        found = g.found
        row = {i: r for r, i in enumerate(found)}
        queries = [i for i in missing if i in row]
        if queries and len(found) > 1:
            expanded, raw = ranking(g.vectors[found])
            rows = [row[i] for i in queries]
            best = nearest(expanded[rows], k, tiebreak=raw[rows])
            pairs |= {tuple(sorted((i, found[int(j)]))) for i, js in zip(queries, best) for j in js}
        lost = [i for i in missing if i not in row]  # neither a position nor descriptors: every pair
        pairs |= {tuple(sorted((i, j))) for i in lost for j in range(len(names)) if j != i}
    return [(names[i], names[j]) for i, j in sorted(pairs)]


_NUMBERED = re.compile(r"^(.*?)(\d+)(\D*)$")


def numbered_sequence(names: list[str]) -> float:
    """The share of `names` (stems) in the largest group of one prefix and suffix around a number whose numbers
    step evenly (frame_00001.jpg, frame_00002.jpg, ...; or every 5th frame): how much the names look like the
    frames of a video."""
    groups: dict[tuple[str, str, str], list[int]] = {}
    for name in names:
        path = Path(name)
        m = _NUMBERED.match(path.stem)
        if m:
            groups.setdefault((str(path.parent), m.group(1), m.group(3) + path.suffix.lower()), []).append(
                int(m.group(2)))
    if not groups or not names:
        return 0.0
    numbers = sorted(max(groups.values(), key=len))
    if len(numbers) < 2:
        return len(numbers) / len(names)
    steps = Counter(np.diff(numbers).tolist())
    step, count = steps.most_common(1)[0]
    return (count + 1) / len(names) if step > 0 else 0.0


def _agrees_with_order(g: GlobalVectors, window: int) -> float:
    """The share of images whose most similar other image is within `window` in name order."""
    found = g.found
    if len(found) < 2:
        return 0.0
    best = nearest(similarities(g.vectors[found]), 1)[:, 0]
    return float(np.mean(np.abs(np.asarray(found) - np.asarray(found)[best]) <= window))


def choose_auto(names: list[str], vectors: _Vectors, positions: Positions | None) -> tuple[str, str]:
    """(spec, reason) that `auto` resolves to for these images (module doc)."""
    n = len(names)
    if n < AUTO_EXHAUSTIVE:
        return "exhaustive", f"{n} images, fewer than {AUTO_EXHAUSTIVE}: every pair"
    if positions is not None:
        located = sum(positions(name) is not None for name in names)
        if located >= AUTO_GPS_SHARE * n:
            return AUTO_SPATIAL, f"{located} of {n} images have a GPS position"
    share = numbered_sequence(names)
    if share >= AUTO_VIDEO_SHARE and vectors.descriptors is not None:
        agree = _agrees_with_order(vectors.get("auto"), AUTO_SEQUENTIAL_K)
        if agree >= AUTO_VIDEO_AGREE:
            return (f"sequential:{AUTO_SEQUENTIAL_K}", f"{share:.0%} of the names are numbered frames and "
                    f"{agree:.0%} of the images look most like a frame within {AUTO_SEQUENTIAL_K}")
        return AUTO_RETRIEVAL, (f"{share:.0%} of the names are numbered frames but only {agree:.0%} of the "
                                f"images look most like a frame within {AUTO_SEQUENTIAL_K}: not a video")
    return AUTO_RETRIEVAL, f"{n} images, no GPS on most and no numbered frame sequence"
