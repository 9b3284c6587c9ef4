"""What every ``twist-*`` command shares: consoles and the error boundary."""

from __future__ import annotations

import logging
import sys

import typer
from rich.console import Console

from twist_data.errors import TwistError

out = Console()
err = Console(stderr=True)


def run_app(app: typer.Typer, log_level: int = logging.WARNING) -> None:
    """Run a Typer app; known errors become one ``error:`` line on stderr and exit code 2.
    ``log_level`` applies to twist's own loggers; other libraries log warnings only."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    for name in ("twist_data", "twist_models"):
        logging.getLogger(name).setLevel(log_level)
    try:
        app()
    except TwistError as exc:
        err.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
        sys.exit(2)
