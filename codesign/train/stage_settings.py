"""The settings that shaped each stage of a multi-stage run, recorded in the stage's folder and compared when a
restart on the same run folder would reuse the stage (issue 59: a killed main job restarted with another
codesign.lsr_max and seed reused the stages made under the old settings and labelled the result with the new ones).

A stage writes stage_settings.json into its folder as it starts, before any of its other files: the run's resolved
config, flattened to dotted keys, less what only changes how a run executes (EXECUTION). A restart reads every
stage folder's record before any work and refuses (ConfigError) when a key the stage depends on differs, naming each
key with both values. A stage folder of an earlier version (files, but no record) is reused as before, with a
warning: its settings cannot be told, and refusing it would strand every killed run of that version.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

from codesign.config import compare
from codesign.config.compare import covered, flat_keys
from codesign.errors import ConfigError
from codesign.io import files as io

log = logging.getLogger("codesign.main_job")

RECORD = "stage_settings.json"
# keys that change how a run executes (where, how fast, what it logs), never what it computes
EXECUTION = ("hydra", "device", "threads", "deterministic", "logging", "debug", "task", "trainer.checkpoint_every",
             "trainer.compile", "trainer.channels_last")
SHOWN = 6  # differing keys named with their values before "and N more"


def settings(values: dict) -> dict:
    """The settings a stage records: the run's config ``values`` (plain containers, interpolations resolved: the
    experiment's to_container) flattened to dotted keys, as JSON stores them (tuples as lists), less EXECUTION."""
    flat = json.loads(json.dumps(flat_keys(values), default=str))
    return {k: v for k, v in flat.items() if not covered(k, EXECUTION)}


def differences(recorded: dict, current: dict, ignored: tuple = ()) -> list[tuple[str, object, object]]:
    """(key, recorded value, current value) for every key of either that differs, but the ``ignored`` keys (a
    prefix such as 'trainer' covers its whole block) and EXECUTION; a key one side lacks shows as ABSENT."""
    return compare.differences(recorded, current, EXECUTION + tuple(ignored))


def read_record(folder: Path) -> dict | None:
    """The settings recorded in ``folder``/RECORD, or None without a record; an unreadable record is a
    ConfigError naming the file (the stage's settings cannot be told)."""
    path = Path(folder) / RECORD
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
        if isinstance(record, dict) and isinstance(record.get("settings"), dict):
            return record["settings"]
    except ValueError:
        pass
    raise ConfigError(str(path), "(unreadable)", "is not a stage settings record: the settings its stage was made "
                      "with cannot be told, so the stage is not reused; start the run in a new folder")


def check_stage(folder: Path, stage: str, current: dict, ignored: tuple = ()) -> None:
    """ConfigError when the stage in ``folder`` was made with other settings than ``current`` (this run's), one
    entry per differing key with both values; a folder of an earlier version (files, no record) is reused with a
    warning; a folder without files is new."""
    folder = Path(folder)
    recorded = read_record(folder)
    if recorded is None:
        if folder.is_dir() and any(folder.iterdir()):
            log.warning("main job: stage %s/ has no %s (made before codesign recorded each stage's settings): it is "
                        "reused as it is, its settings unchecked; to be sure of them, start a new run folder",
                        stage, RECORD)
        return
    differ = differences(recorded, current, ignored)
    if not differ:
        return
    key, old, new = differ[0]
    raise ConfigError(key, new, f"the stage {stage}/ of this run folder ({folder.parent}) was made with other "
                      f"settings, which a restart would reuse under this run's: {compare.described(differ, SHOWN)}; a stage is reused only "
                      f"with the settings it was made with: restart with those, or start this run in a new folder "
                      f"(hydra.run.dir=PATH, or leave it unset: every run gets a new one)")


def begin_stage(folder: Path, stage: str, current: dict) -> None:
    """Record ``current`` as the settings of the stage starting in ``folder`` (created), before any other file of
    it; a stage that holds a record keeps it (check_stage found it equal), and one of an earlier version's (files,
    no record) gets none: what its files were made with is unknown."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if read_record(folder) is None and not any(folder.iterdir()):
        io.write_json(folder / RECORD, {"stage": stage, "settings": current})
