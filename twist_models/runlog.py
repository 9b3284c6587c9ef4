"""Run records shared by the collector and the distiller: CSV rows and TensorBoard scalars."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any


def append_csv(path: Path, row: dict[str, Any], columns: tuple[str, ...]) -> None:
    """Append one row with fixed ``columns`` (missing values empty), header on first write."""
    new = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, restval="", extrasaction="ignore")
        if new:
            writer.writeheader()
        writer.writerow(row)


class Board:
    """TensorBoard scalars when the ``tensorboard`` package is installed; otherwise nothing
    (the CSV files are the record either way)."""

    def __init__(self, folder: Path) -> None:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            self._writer = None
        else:
            self._writer = SummaryWriter(str(folder / "tensorboard"))

    def scalar(self, tag: str, value: float, step: int) -> None:
        if self._writer is not None:
            self._writer.add_scalar(tag, value, step)
            self._writer.flush()
