"""What the stages share: the front end's config, the number of workers, the workspace each stage holds."""

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cameras import CameraConfig
from ..config import bounded
from ..executor import default_workers
from ..features.sift import SiftConfig
from ..matching.matcher import MatcherConfig
from ..matching.verify import VerifyConfig
from ..workspace import Workspace


@dataclass(frozen=True)
class FrontendConfig:
    """Everything that decides the features and matches of a run (see each part's own defaults)."""

    camera: CameraConfig = CameraConfig()
    sift: SiftConfig = SiftConfig()
    pairs: str = "auto"  # auto | exhaustive | sequential:K | spatial:K[:R] | retrieval:K | A+B | pairs file
    matcher: MatcherConfig = MatcherConfig()
    verify: VerifyConfig = VerifyConfig()
    workers: int = bounded(0, 0, hash=False)  # processes/threads; 0 = all cores
    # folder of masks (io/masks.py); out of the hash, so that runs without masks keep their records, and
    # recorded by the features stage and reconstruct's hash when given
    masks: str = field(default="", metadata={"hash": False})
    # a CSV file of camera positions (io/pose_priors.py) that replaces the images' EXIF GPS as the database's pose
    # priors; out of the hash like `masks`, and recorded in reconstruct's hash by its content when given
    pose_priors: str = field(default="", metadata={"hash": False})


def worker_count(config: FrontendConfig) -> int:
    """The processes or threads the features and matching stages run: `config.workers`, 0 = all cores."""
    return config.workers if config.workers > 0 else default_workers()


def as_workspace(workspace: Workspace | Path | str) -> Workspace:
    """`workspace` as a Workspace (a path is opened as one)."""
    return workspace if isinstance(workspace, Workspace) else Workspace(workspace)


def holding_workspace(func: Callable) -> Callable:
    """`func(config, workspace, ...)` run with the workspace locked against other processes (Workspace.lock)."""
    @functools.wraps(func)
    def run(config, workspace, *args, **kwargs):
        with as_workspace(workspace).lock():
            return func(config, workspace, *args, **kwargs)
    return run


def stats_text(values: Sequence[float] | np.ndarray) -> str:
    """Mean, min and max of `values` in one phrase, for the stages' summaries."""
    v = np.asarray(values, dtype=float)
    if not v.size:
        return "none"
    return f"{v.mean():.0f} on average (min {v.min():.0f}, max {v.max():.0f})"
