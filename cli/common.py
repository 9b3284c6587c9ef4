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
    """Run a Typer app; known errors become one ``error:`` line on stderr and exit code 2."""
    logging.basicConfig(level=log_level, format="%(levelname)s %(name)s: %(message)s")
    try:
        app()
    except TwistError as exc:
        err.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
        sys.exit(2)
