"""Errors that reach the user as one line and a non-zero exit code.

Library code raises these instead of printing; `cli.py` turns them into `mvrecon: error: ...` and exit code 2.
"""


class InputError(Exception):
    """Bad input from the user (a wrong path, a corrupt image, too few images, a mismatched config)."""

    exit_code = 2


class DiskFull(InputError):
    """No room left to write on: the run stops, and what it wrote so far is kept for the rerun."""

    advice = "free some space and run the command again: what it did so far is kept"
