"""The workspace folder of one run: `database.db` (COLMAP's schema) and `config.json` (each stage's config + hash).

Results are only reused when they were made with the same settings. Each stage (features, matching, later
mapping) records its config dict and hash when it starts; a rerun with the same config resumes, a different one is
refused with a message that names the differing fields, unless `overwrite` is set. Overwriting a stage also drops
the record of every stage recorded after it, because their results were built on the old one; the caller clears
the matching database tables (`begin_stage` returns the names of the stages it dropped).
"""

from pathlib import Path

from . import config as cfgmod
from .errors import InputError
from .io.files import hold_folder, read_json_object, write_json

REDO = "rerun with --overwrite to recompute, or use another workspace"  # what a refused stage config advises


class Workspace:
    def __init__(self, path):
        self.path = Path(path)

    @property
    def database_path(self) -> Path:
        return self.path / "database.db"

    @property
    def config_path(self) -> Path:
        return self.path / "config.json"

    @property
    def snapshot_path(self) -> Path:
        """The mapper's last snapshot (for --resume)."""
        return self.path / "snapshots" / "mapper.pkl"

    def create(self) -> "Workspace":
        if self.path.exists() and not self.path.is_dir():
            raise InputError(f"{self.path}: workspace exists and is not a folder")
        self.path.mkdir(parents=True, exist_ok=True)
        return self

    def lock(self):
        """Hold the workspace for the block against another mvrecon process (`io.files.hold_folder`)."""
        return hold_folder(self.path)

    def stages(self) -> dict:
        """{stage: {"hash": ..., "config": {...}}} in the order the stages were first run."""
        if not self.config_path.is_file():
            return {}
        data = read_json_object(self.config_path)
        stages = data.get("stages", {}) if data is not None else None
        if isinstance(stages, dict) and all(isinstance(r, dict) and isinstance(r.get("hash"), str)
                                            and isinstance(r.get("config"), dict) for r in stages.values()):
            return stages
        raise InputError(f"{self.config_path}: not a valid workspace config (use --overwrite to start the "
                         "workspace over)")

    def stage_config(self, stage: str) -> dict | None:
        record = self.stages().get(stage)
        return None if record is None else record["config"]

    def require_stage(self, stage: str, hint: str) -> dict:
        """The stored config of a stage that must have run already; otherwise an InputError with `hint`."""
        found = self.stage_config(stage)
        if found is None or not self.database_path.is_file():
            raise InputError(f"{self.path}: no {stage} in this workspace; {hint}")
        return found

    def check_stage(self, stage: str, config: dict, overwrite: bool = False, *, hint: str = REDO) -> list[str]:
        """What `begin_stage` would return, without writing anything: a refused config raises here, before the
        caller deletes or rewrites any result, with `hint` after the differences (the command that redoes only
        this stage, say)."""
        return self._plan(stage, config, overwrite, hint)[1]

    def _plan(self, stage: str, config: dict, overwrite: bool, hint: str = REDO) -> tuple[dict, list[str]]:
        try:
            stages, dropped = self.stages(), []
        except InputError:
            if not overwrite:
                raise
            stages, dropped = {}, [stage]  # no record of what the results were made with: --overwrite redoes them
        if stage == "features" and stage not in stages and self.database_path.exists():
            # features in a database this workspace has no record of (another tool's): what is recorded after
            # them (a `map -w` of that database) was made from it, so --overwrite redoes it all
            if not overwrite:
                raise InputError(f"{self.database_path}: a database without mvrecon's record of how its features "
                                 f"were made (another tool's, say); map it with `mvrecon map -o {self.path}`, or "
                                 "rerun with --overwrite to start over")
            return {}, [stage, *stages]
        names = list(stages)
        new_hash = cfgmod.config_hash(config)
        if stage in stages:
            if stages[stage]["hash"] == new_hash and not overwrite:
                return stages, []
            if not overwrite:
                changes = cfgmod.diff(stages[stage]["config"], config)
                raise InputError(f"{self.path}: made with a different {stage} config ({'; '.join(changes)}); "
                                 f"{hint}")
            dropped = names[names.index(stage):]
            for name in dropped:
                del stages[name]
        return stages, dropped

    def begin_stage(self, stage: str, config: dict, overwrite: bool = False) -> list[str]:
        """Record `config` for `stage`. Returns the stages (this one and later ones) whose results must be cleared:
        [] when resuming with the same config or starting fresh, and refuses a different config unless overwrite.
        Redoing a stage before mapping also deletes the mapper's snapshot: it was mapped from the old results."""
        self.create()
        stages, dropped = self._plan(stage, config, overwrite)
        if dropped and stage != "mapping":
            self.snapshot_path.unlink(missing_ok=True)
        stages[stage] = {"hash": cfgmod.config_hash(config), "config": config}
        self._write(stages)
        return dropped

    def _write(self, stages: dict) -> None:
        write_json(self.config_path, {"stages": stages}, indent=2)
