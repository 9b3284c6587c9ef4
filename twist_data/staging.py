"""New datasets built aside: a command that writes a new folder builds it under a hidden name
beside it and renames it into place only when complete, so that the folder holds nothing or
the whole, whatever stops the command."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from twist_data.errors import ConfigError


def require_new_folder(out: Path) -> None:
    """Refuse an output that exists and is not an empty folder (nothing is overwritten)."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"output {str(out)!r} exists and is not an empty folder")


@contextmanager
def built_aside(out: Path, purpose: str) -> Iterator[Path]:
    """The hidden folder ``.<out>.<purpose>-<pid>`` to build ``out`` in: renamed to ``out``
    when the block ends, removed when it raises."""
    require_new_folder(out)
    staging = out.parent / f".{out.name}.{purpose}-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        yield staging
        if out.exists():
            out.rmdir()
        os.rename(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
