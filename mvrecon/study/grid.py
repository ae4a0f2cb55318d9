"""The study grid: which degradations are varied, at which levels, and the name of each cell on disk.

A study varies one degradation at a time from the clean images (the other parameters stay at the base values),
so each panel of the report shows one cause. A level that changes nothing (noise 0, blur 0) is the clean cell,
shared by every degradation, so it is run once per engine. Cell names are stable ("noise-10", "jpeg-75"), which is
what lets a wider grid reuse the cells an earlier, narrower one computed.
"""

from dataclasses import dataclass

from ..errors import InputError
from .degrade import Degradation, with_level

CLEAN = "clean"


@dataclass(frozen=True)
class Axis:
    """One degradation a study can vary: its CLI name, the Degradation field it sets, and how to label it."""

    name: str
    field: str
    label: str
    identity: float  # the level that leaves images unchanged


AXES = {a.name: a for a in (
    Axis("noise", "noise_sigma", "Gaussian noise sigma (grey levels)", 0.0),
    Axis("poisson", "poisson_peak", "Poisson noise peak (electrons at white)", 0.0),
    Axis("blur", "blur_sigma", "Gaussian blur sigma (px)", 0.0),
    Axis("motion", "motion_length", "motion blur length (px)", 0.0),
    Axis("jpeg", "jpeg_quality", "JPEG quality", 0.0),
    Axis("sharpen", "sharpen_amount", "unsharp mask amount", 0.0),
    Axis("downscale", "downscale", "downscale factor", 1.0),
    Axis("gamma", "gamma", "gamma", 1.0),
    Axis("brightness", "brightness", "brightness gain", 1.0),
)}


@dataclass(frozen=True)
class Cell:
    """One image set of the study: a degradation at a level, or the clean images (axis None)."""

    axis: str | None
    level: float | None

    @property
    def key(self) -> str:
        return CLEAN if self.axis is None else f"{self.axis}-{self.level:g}"

    @property
    def is_clean(self) -> bool:
        return self.axis is None

    def degradation(self, base: Degradation) -> Degradation:
        """`base` (a degrade.Degradation) with this cell's level set."""
        return base if self.is_clean else with_level(base, AXES[self.axis].field, self.level)


def parse_levels(axis: str, text: str) -> tuple[float, ...]:
    """'0,5,10' -> (0.0, 5.0, 10.0), in the order given (the user lists them from mild to severe)."""
    try:
        levels = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise InputError(f"--{axis} {text}: expected comma-separated numbers, e.g. 0,5,10") from None
    if not levels:
        raise InputError(f"--{axis}: no levels given")
    if len(set(levels)) != len(levels):
        raise InputError(f"--{axis} {text}: a level is repeated")
    for level in levels:
        if level != AXES[axis].identity:
            with_level(Degradation(), AXES[axis].field, level)  # raises InputError on an impossible level
    return levels


@dataclass(frozen=True)
class Grid:
    """Degradation name -> levels, in the order given (mild to severe); the clean cell is implied."""

    levels: dict

    def __post_init__(self):
        unknown = sorted(set(self.levels) - set(AXES))
        if unknown:
            raise InputError(f"unknown degradation(s) {', '.join(unknown)}; known: {', '.join(AXES)}")
        if not self.levels:
            raise InputError("the study grid is empty: give at least one of " + ", ".join(f"--{a}" for a in AXES))

    def axes(self) -> list[str]:
        return list(self.levels)

    def degraded_levels(self, axis: str) -> list[float]:
        """The levels of `axis` that change the images (its identity level is the clean cell)."""
        return [lv for lv in self.levels[axis] if lv != AXES[axis].identity]

    def cells(self) -> list[Cell]:
        """The clean cell first, then each degradation's levels; every image set once."""
        out = [Cell(None, None)]
        for axis in self.levels:
            out += [Cell(axis, lv) for lv in self.degraded_levels(axis)]
        return out
