"""One progress bar style for every long stage (stderr, hidden with -q or when logging is quiet)."""

import logging

from tqdm import tqdm

_enabled = True


def set_enabled(enabled: bool) -> None:
    global _enabled
    _enabled = enabled


def progress(iterable=None, *, total=None, desc: str = "", unit: str = "it"):
    """Wrap an iterable (or make a bar to `update()` by hand) with the project's progress bar."""
    disable = not _enabled or logging.getLogger("mvrecon").getEffectiveLevel() > logging.INFO
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=disable, dynamic_ncols=True, leave=False)
