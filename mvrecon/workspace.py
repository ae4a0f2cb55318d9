"""The workspace folder of one run: `database.db` (COLMAP's schema) and the record of its stages
(`.stages/record.json`, an `io.record.Record`: each stage's config, keyed on its `config.config_hash`).

Results are only reused when they were made with the same settings. Each stage (features, matching, later
mapping) records its config when it starts; a rerun with the same config resumes, a different one is refused
with a message that names the differing fields, unless `overwrite` is set. Overwriting a stage also drops the
record of every stage recorded after it, because their results were built on the old one; the caller clears
the matching database tables (`begin_stage` returns the names of the stages it dropped). A workspace whose
record is damaged, or written by an older mvrecon (`config.json`), is refused the same way: `overwrite` starts
it over.
"""

from contextlib import AbstractContextManager
from pathlib import Path

from .config import config_hash
from .errors import InputError
from .io.files import hold_folder
from .io.record import FOLDER as RECORD_FOLDER
from .io.record import Record

REDO = "rerun with --overwrite to recompute, or use another workspace"  # what a refused stage config advises
LEGACY = "config.json"  # where an older mvrecon kept the stages' configs, in a format no longer read


class Workspace:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    @property
    def database_path(self) -> Path:
        return self.path / "database.db"

    @property
    def record_path(self) -> Path:
        """The record of the stages run (`io.record.Record`)."""
        return self.path / RECORD_FOLDER / "record.json"

    @property
    def snapshot_path(self) -> Path:
        """The mapper's last snapshot (for --resume)."""
        return self.path / "snapshots" / "mapper.pkl"

    def create(self) -> "Workspace":
        if self.path.exists() and not self.path.is_dir():
            raise InputError(f"{self.path}: workspace exists and is not a folder")
        self.path.mkdir(parents=True, exist_ok=True)
        return self

    def lock(self) -> AbstractContextManager[Path]:
        """Hold the workspace for the block against another mvrecon process (`io.files.hold_folder`)."""
        return hold_folder(self.path)

    def _record(self) -> Record:
        return Record(self.path)

    def _checked_record(self) -> Record:
        """The record, or an InputError when it cannot tell what the results were made with."""
        record = self._record()
        if record.damaged or any(record.config(name) is None for name in record.names()):
            raise InputError(f"{record.path}: not a valid workspace record (use --overwrite to start the "
                             "workspace over)")
        legacy = self.path / LEGACY
        if not record.path.exists() and legacy.is_file():
            raise InputError(f"{legacy}: a workspace of an older mvrecon version, whose record is not read any "
                             "more; rerun with --overwrite to start the workspace over, or use another workspace")
        return record

    def stages(self) -> dict:
        """{stage: {"hash": ..., "config": {...}}} in the order the stages were first run."""
        record = self._checked_record()
        return {name: {"hash": record.key(name), "config": record.config(name)} for name in record.names()}

    def stage_config(self, stage: str) -> dict | None:
        return self._checked_record().config(stage)

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

    def _plan(self, stage: str, config: dict, overwrite: bool,
              hint: str = REDO) -> tuple[Record | None, list[str]]:
        """(the record, the stages to drop): refuses a different config unless `overwrite`; no record when the
        one there cannot be read (and `overwrite` starts it over)."""
        try:
            record, dropped = self._checked_record(), []
        except InputError:
            if not overwrite:
                raise
            return None, [stage]  # no record of what the results were made with: --overwrite redoes them
        names = record.names()
        if stage == "features" and stage not in names and self.database_path.exists():
            # features in a database this workspace has no record of (another tool's): what is recorded after
            # them (a `map -w` of that database) was made from it, so --overwrite redoes it all
            if not overwrite:
                raise InputError(f"{self.database_path}: a database without mvrecon's record of how its features "
                                 f"were made (another tool's, say); map it with `mvrecon map -o {self.path}`, or "
                                 "rerun with --overwrite to start over")
            return record, [stage, *names]
        if stage in names:
            changes = record.differences(stage, config)
            if not changes and not overwrite:
                return record, []
            if not overwrite:
                raise InputError(f"{self.path}: made with a different {stage} config ({'; '.join(changes)}); "
                                 f"{hint}")
            dropped = names[names.index(stage):]
        return record, dropped

    def begin_stage(self, stage: str, config: dict, overwrite: bool = False) -> list[str]:
        """Record `config` for `stage`. Returns the stages (this one and later ones) whose results must be cleared:
        [] when resuming with the same config or starting fresh, and refuses a different config unless overwrite.
        Redoing a stage before mapping also deletes the mapper's snapshot: it was mapped from the old results."""
        self.create()
        record, dropped = self._plan(stage, config, overwrite)
        if dropped and stage != "mapping":
            self.snapshot_path.unlink(missing_ok=True)
        if record is None:  # --overwrite past a record that could not be read
            record = self._record()
            record.clear()
            (self.path / LEGACY).unlink(missing_ok=True)
        record.drop(*dropped)
        record.put(stage, config_hash(config), config=config)
        return dropped
