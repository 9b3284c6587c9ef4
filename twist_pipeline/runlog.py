"""What the collector, the distiller and the baselines share about their run folders: one
lifecycle (:class:`RunFolder`: the folder checked or created, a finished or running run refused
unless resumed, a resumed run refused when its config changed, naming both values, the config
stored as JSON), CSV rows and TensorBoard scalars."""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from twist_data.errors import ConfigError, TwistError
from twist_data.staging import require_writable
from twist_models.config import from_json, json_leaves, removed_fields, to_json, with_moved

T = TypeVar("T")


def append_csv(path: Path, row: dict[str, Any], columns: tuple[str, ...]) -> None:
    """Append one row with fixed ``columns`` (missing values empty), header on first write. A
    file that exists keeps its own header's columns (one written by an older version, resumed,
    stays a valid table)."""
    new = not path.exists()
    if not new:
        with path.open(newline="") as f:
            columns = tuple(next(csv.reader(f), None) or columns)
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, restval="", extrasaction="ignore")
        if new:
            writer.writeheader()
        writer.writerow(row)


class TensorBoardLog:
    """TensorBoard scalars and images under ``folder/tensorboard`` when the ``tensorboard``
    package is installed (``pip install twist[tensorboard]``); otherwise nothing: the CSV
    files are the record either way. Events are flushed at most every ``flush_seconds`` (and
    on :meth:`close`), not at every write: a crash loses at most that much of the board."""

    def __init__(self, folder: Path, flush_seconds: float = 30.0) -> None:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            self._writer = None
        else:
            self._writer = SummaryWriter(str(folder / "tensorboard"), flush_secs=flush_seconds)

    @property
    def enabled(self) -> bool:
        return self._writer is not None

    def scalar(self, tag: str, value: float, step: int) -> None:
        if self._writer is not None:
            self._writer.add_scalar(tag, value, step)

    def image(self, tag: str, png: Path, step: int) -> None:
        """The picture in the file ``png`` (a plot the run has just written) under ``tag``."""
        if self._writer is None:
            return
        import cv2

        picture = cv2.imread(str(png), cv2.IMREAD_COLOR)
        if picture is not None:
            self._writer.add_image(tag, picture[..., ::-1].copy(), step, dataformats="HWC")

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None


def check_output(out: Path, error: type[TwistError]) -> None:
    """Refuse, with ``error`` and without creating anything, an output folder ``out`` that
    is a file or could not be created or written (:func:`~twist_data.staging.require_writable`)."""
    if out.exists() and not out.is_dir():
        raise error(f"output {str(out)!r} exists and is not a folder")
    try:
        require_writable(out, "output folder")
    except ConfigError as exc:
        raise error(str(exc)) from None


def prepare_output(out: Path, error: type[TwistError]) -> None:
    """Create the output folder ``out`` if needed; refuse, with ``error``, a file in its place,
    a folder that cannot be created, or one that is not writable."""
    if out.exists() and not out.is_dir():
        raise error(f"output {str(out)!r} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise error(f"cannot create output folder {str(out)!r}: {exc.strerror}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise error(f"output folder {str(out)!r} is not writable")


def resume_conflicts(before: Mapping[str, Any], config: Any,
                     mutable: tuple[str, ...]) -> list[str]:
    """``name was X, now Y`` for every field of the config dataclass ``config`` outside
    ``mutable`` (dotted names reach nested configs) that a resumed run would change, against
    ``before``, the run's stored config (JSON). A field ``before`` lacks was added after that
    run began; every new field's default keeps the behaviour of the versions before it, so the
    run is compared with that default. A field since moved into a nested config is compared
    where it is now, and one since removed conflicts unless the run left it off
    (:func:`~twist_models.config.moved_fields`, :func:`~twist_models.config.removed_fields`)."""
    kind = type(config)
    was_removed = {name: before[name] for name, off in removed_fields(kind).items()
                   if name in before and before[name] != off}
    before = json_leaves(with_moved(kind, before))
    defaults = json_leaves(to_json(kind()))
    conflicts = []
    for name, value in json_leaves(to_json(config)).items():
        was = before.get(name, defaults.get(name))
        if name not in mutable and was != value:
            conflicts.append(f"{name} was {was!r}, now {value!r}")
    conflicts += [f"{name} was {value!r} and has been removed"
                  for name, value in was_removed.items()]
    return conflicts


def refuse_resume(conflicts: list[str], error: type[TwistError],
                  may_change: str = "--steps") -> None:
    """Raise ``error`` naming every conflict, if there is any; ``may_change`` names the options
    that a resumed run may change."""
    if conflicts:
        raise error(f"--resume with a different config ({'; '.join(conflicts)}); only "
                    f"{may_change} may change when resuming")


@dataclass(frozen=True)
class RunFolder:
    """One stage's run folder and its stored ``config.json``."""

    path: Path
    """The folder."""
    section: str
    """The key under which ``config.json`` holds the stage's own config (e.g. ``distil``)."""
    error: type[TwistError]
    """The stage's exception type for every refusal."""
    what: str
    """What the folder holds, for messages (e.g. ``a distillation run``)."""

    @property
    def config_file(self) -> Path:
        return self.path / "config.json"

    @property
    def latest(self) -> Path:
        """The resume point: the newest checkpoint of the run."""
        return self.path / "latest.pt"

    def stored(self) -> dict[str, Any] | None:
        """The stored ``config.json``, or None before the run's first write."""
        return json.loads(self.config_file.read_text()) if self.config_file.exists() else None

    def open(self, config: Any, resume: bool, may_change: tuple[str, ...],
             may_change_options: str = "--steps", also: Sequence[str] = ()) -> None:
        """Before anything is written: create or check the folder; refuse a folder that holds
        a run unless ``resume``; on resume, refuse a ``config`` whose fields outside
        ``may_change`` differ from the stored ones (``also``: further conflicts the stage
        found), naming every one with both values."""
        prepare_output(self.path, self.error)
        before = self.stored()
        if before is not None and not resume:
            raise self.error(f"{str(self.path)!r} already holds {self.what}; pass --resume to "
                             "continue it, or another --out")
        if resume and before is not None:
            conflicts = resume_conflicts(record_section(before, self.section, type(config)),
                                         config, may_change)
            refuse_resume([*conflicts, *also], self.error, may_change_options)

    def write_config(self, config: Any, **context: Any) -> None:
        """Store ``config`` under :attr:`section` beside ``context`` (further configs as
        dataclasses, paths, counts), atomically."""
        sections = {self.section: to_json(config)}
        sections.update({k: to_json(v) if hasattr(v, "__dataclass_fields__") else
                         str(v) if isinstance(v, Path) else v for k, v in context.items()})
        partial = self.config_file.with_suffix(".json.partial")
        partial.write_text(json.dumps(sections, indent=2))
        os.replace(partial, self.config_file)


def record_section(record: Mapping[str, Any], section: str, config_type: type) -> dict[str, Any]:
    """The ``section`` of a run's ``config.json`` as ``config_type`` stores it now: its own
    ``record_section`` where it keeps older records loading (a field whose place moved beyond
    what :func:`~twist_models.config.moved_fields` reaches), else the section as recorded."""
    upgrade = getattr(config_type, "record_section", None)
    return upgrade(record) if upgrade is not None else dict(record[section])


def recorded_config(path: str | os.PathLike[str], section: str, config_type: type[T]) -> T:
    """The ``config_type`` config that a run recorded under ``section`` of its
    ``config.json`` (``path``: the file or the run's folder), to start another run from. A
    missing or unreadable file, or the config of another kind of run, is a
    :class:`ConfigError` naming the file."""
    path = Path(path)
    file = path / "config.json" if path.is_dir() else path
    if not file.is_file():
        raise ConfigError(f"config file {str(file)!r} does not exist")
    try:
        data = json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"config file {str(file)!r} is not a run's JSON config: {exc}"
                          ) from None
    if not isinstance(data, dict) or section not in data:
        kinds = [k for k in ("collect", "distil", "baseline")
                 if isinstance(data, dict) and k in data]
        what = f"a {kinds[0]} run's config" if kinds else "not a twist run's config"
        raise ConfigError(f"config file {str(file)!r} is {what}; this command starts from a "
                          f"{section} run's")
    try:
        return from_json(config_type, record_section(data, section, config_type))
    except (ConfigError, TypeError, ValueError, KeyError) as exc:
        raise ConfigError(f"config file {str(file)!r}: {exc}") from None
