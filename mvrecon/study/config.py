"""The settings every cell of a degradation study shares (`StudyConfig`), kept apart from the study's running
(study.py) so that its report (report.py) can name them too."""

from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from ..eval.runners import RunOptions
from .degrade import Degradation
from .grid import Grid


@dataclass(frozen=True)
class StudyConfig:
    """What every cell of a study shares; a study folder keeps one config (the grid and engines may grow)."""

    images: Path  # the clean images
    gt: Path | None = None  # ground truth (any format eval.ground_truth reads); None: each engine's clean model
    engines: tuple[str, ...] = ("mvrecon", "colmap")
    seed: int = 0  # the degradations' noise and both engines' RANSAC/mapper seed
    base: Degradation = field(default_factory=Degradation)  # parameters not varied (e.g. the motion angle)
    run_options: RunOptions = field(default_factory=RunOptions)
    jobs: int = 0  # cells run at the same time; 0: the machine's cores
    timeout_s: float | None = None  # per engine run; a run past it counts as failed

    def identity(self) -> dict:
        """The settings that make cells comparable (the engines, jobs and timeout may change between runs)."""
        return {"images": str(Path(self.images).resolve()), "gt": str(Path(self.gt).resolve()) if self.gt else None,
                "seed": self.seed, "base": self.base.to_dict(), "run_options": self.run_options.to_dict()}

    def check_grid(self, grid: Grid, downscale: str | None = None) -> None:
        """An InputError when `grid` makes smaller copies of the images while a run option holds for the clean
        images' size only (camera params, masks). `downscale`: its levels as given (--downscale), for the
        message."""
        if "downscale" not in grid.levels or not grid.degraded_levels("downscale"):
            return
        if self.run_options.camera_params:
            raise InputError(f"--camera-params with --downscale {downscale}: the params hold for the clean "
                             "images' size, not for the smaller copies; study the downscale without "
                             "--camera-params")
        if self.run_options.masks:
            raise InputError(f"--masks with --downscale {downscale}: the masks fit the clean images' size, "
                             "not the smaller copies; study the downscale without --masks")
