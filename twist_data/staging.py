"""New datasets built aside: a command that writes a new folder builds it under a hidden name
beside it and renames it into place only when complete, so that the folder holds nothing or
the whole, whatever stops the command."""

from __future__ import annotations

import os
import shutil
import tempfile
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


def nearest_existing(path: Path) -> Path:
    """``path`` or the closest folder above it that exists."""
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def require_writable(path: Path, what: str = "output") -> None:
    """Refuse, before any work and without creating anything, an output path that cannot be
    written: the closest folder at or above it that exists must take a new file. It is probed
    by creating and removing one, since permission bits say nothing of ``/proc`` or of a
    read-only mount for root."""
    path = Path(path)
    folder = path.parent if path.exists() and not path.is_dir() else nearest_existing(path)
    if not folder.is_dir():
        raise ConfigError(f"{what} {str(path)!r} cannot be written: {str(folder)!r} is a file, "
                          "not a folder")
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".twist-probe-"):
            pass
    except OSError as exc:
        raise ConfigError(f"{what} {str(path)!r} cannot be written in {str(folder)!r}: "
                          f"{exc.strerror or exc}") from None


def require_new_file(path: Path, overwrite: bool, what: str = "output") -> None:
    """Refuse an output file that exists unless ``overwrite`` (the CLI's ``--overwrite``), and
    any output that cannot be written (:func:`require_writable`)."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{what} {str(path)!r} is a folder; name a file")
    if path.exists() and not overwrite:
        raise ConfigError(f"{what} {str(path)!r} exists; pass --overwrite to replace it")
    require_writable(path, what)


def machine_memory() -> int:
    """Bytes of physical memory on this machine."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def require_memory(needed: float, what: str, available: int | None = None) -> None:
    """Refuse work whose arrays alone need more than the machine's physical memory (or
    ``available`` bytes), naming both figures."""
    have = machine_memory() if available is None else available
    if needed > have:
        raise ConfigError(f"{what} needs {human_bytes(needed)} of memory; this machine has "
                          f"{human_bytes(have)}")


def human_bytes(n: float) -> str:
    """``n`` bytes in B, KiB, MiB, GiB, TiB or PiB, one decimal."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} PiB"


def require_disk(needed: float, path: Path, what: str) -> None:
    """Refuse work that would write more than the free space where ``path`` lies, naming both
    figures."""
    free = shutil.disk_usage(nearest_existing(Path(path))).free
    if needed > free:
        raise ConfigError(f"{what} needs about {human_bytes(needed)} of disk; "
                          f"{str(nearest_existing(Path(path)))!r} has {human_bytes(free)} free")


@contextmanager
def removed_on_failure(out: Path) -> Iterator[None]:
    """Undo what a command's set-up wrote into the folder ``out`` if the block raises: a folder
    that did not exist is removed, one that was empty is emptied again; one that held
    anything (a run being resumed) is left as it is."""
    out = Path(out)
    existed = out.exists()
    was_empty = existed and out.is_dir() and not any(out.iterdir())
    try:
        yield
    except BaseException:
        if not existed:
            shutil.rmtree(out, ignore_errors=True)
        elif was_empty:
            for child in out.iterdir():
                if child.is_dir() and not child.is_symlink():
                    shutil.rmtree(child, ignore_errors=True)
                else:
                    child.unlink(missing_ok=True)
        raise
