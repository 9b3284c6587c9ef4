"""What every ``twist-*`` command shares: consoles and the error boundary."""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
import types
import typing
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeRemainingColumn

from twist_data.errors import ConfigError, TwistError
from twist_models.config import field_types, from_json, moved_fields

P = TypeVar("P")
T = TypeVar("T")

out = Console()
err = Console(stderr=True)


def print_json(value: Any, indent: int | None = 2) -> None:
    """``value`` as JSON on stdout, exactly: never wrapped at the terminal's width, nor read
    as Rich markup (a long path or a list in brackets would otherwise break the JSON)."""
    out.print(json.dumps(value, indent=indent), markup=False, highlight=False, soft_wrap=True)


def new_app(**settings: Any) -> typer.Typer:
    """A Typer app with twist's settings. Help is plain text: Rich markup would swallow the
    ``[default]`` notes the options' help strings carry (``[train]``, ``[the preset's]``)."""
    return typer.Typer(add_completion=False, pretty_exceptions_enable=False,
                       rich_markup_mode=None, **settings)


#: What the ``sim`` extra installs: a command that needs it, run without it, says so.
SIM_MODULES = ("mujoco", "dm_control")
#: The library packages whose loggers a command sets to its level (its stages' progress).
LIBRARY_PACKAGES = ("twist_data", "twist_sim", "twist_models", "twist_pipeline")


def run_app(app: typer.Typer, log_level: int = logging.WARNING) -> None:
    """Run a Typer app; known errors become one ``error:`` line on stderr and exit code 2.
    ``log_level`` applies to twist's own loggers; other libraries log warnings only."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    for name in LIBRARY_PACKAGES:
        logging.getLogger(name).setLevel(log_level)
    try:
        # Not standalone: usage errors come here, to be said in one line like every other.
        code = app(standalone_mode=False)
    except TwistError as exc:
        err.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
        sys.exit(2)
    except typer.BadParameter as exc:
        err.print(f"error: {bad_value(exc, sys.argv[1:])}", markup=False, highlight=False,
                  soft_wrap=True)
        sys.exit(2)
    except typer.Abort:
        sys.exit(1)
    except ModuleNotFoundError as exc:
        if exc.name is None or exc.name.split(".")[0] not in SIM_MODULES:
            raise
        err.print(f"error: this command simulates or renders, which needs the sim extra "
                  f"(pip install 'twist[sim]'); {exc.name!r} is not installed", markup=False,
                  highlight=False, soft_wrap=True)
        sys.exit(2)
    except Exception as exc:  # the other usage errors: unknown option, missing argument
        if not hasattr(exc, "format_message"):
            raise
        err.print(f"error: {exc.format_message()} (see --help)", markup=False,
                  highlight=False, soft_wrap=True)
        sys.exit(2)
    if isinstance(code, int) and code:
        sys.exit(code)


def bad_value(exc: typer.BadParameter, args: list[str]) -> str:
    """One sentence for a value the command line could not take, with the value itself."""
    if not exc.message:  # a missing option or argument
        return f"{exc.format_message()} (see --help)"
    opts = list(getattr(exc.param, "opts", []) or [])
    given = None
    for i, arg in enumerate(args):
        for opt in opts:
            if arg == opt and i + 1 < len(args):
                given = args[i + 1]
            elif arg.startswith(f"{opt}="):
                given = arg[len(opt) + 1:]
    name = opts[0] if opts else (exc.param_hint or "a value")
    value = f" {given!r}" if given is not None else ""
    return f"invalid value{value} for {name}: {exc.message}"


@contextmanager
def progress_bar(quiet: bool, description: str,
                 describe: Callable[[P], tuple[int, int, str]]
                 ) -> Iterator[Callable[[P], None] | None]:
    """A Rich bar on stderr with an ETA; the yielded callback takes a library progress report,
    which ``describe`` turns into (done, total, text). Yields None when ``quiet``. The bar
    appears at the first report, so a refusal before any work is the only line printed."""
    if quiet:
        yield None
        return
    bar = Progress(TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(),
                   TextColumn("{task.fields[stats]}"), TimeRemainingColumn(), console=err)
    task = bar.add_task(description, total=None, stats="")
    started = False

    def report(progress: P) -> None:
        nonlocal started
        if not started:
            bar.start()
            started = True
        done, total, stats = describe(progress)
        bar.update(task, completed=done, total=total, stats=stats)

    try:
        yield report
    finally:
        if started:
            bar.stop()


def parse_list(text: str, kind: Callable[[str], T], option: str) -> list[T]:
    """A comma-separated option value as a list; a bad element is one error naming ``option``."""
    try:
        return [kind(s.strip()) for s in text.split(",") if s.strip()]
    except ValueError:
        raise ConfigError(f"{option} must be a comma-separated list, got {text!r}") from None


def parse_settings(pairs: list[str], config_type: type) -> dict[str, Any]:
    """``--set KEY=VALUE`` options as overrides of ``config_type``'s fields (a nested config's
    by dotted keys, ``optim.grad_clip=50``), for :func:`~twist_models.config.replace_fields`;
    each VALUE is read as JSON (numbers, true/false, null) or else taken as a string."""
    hints = field_types(config_type)
    fields = set(hints)
    # A field's name from before it moved into a nested config, or a short name of a nested
    # field (a config's ``ALIASES``), reaches it there.
    names = {**moved_fields(config_type), **getattr(config_type, "ALIASES", {})}
    settings: dict[str, Any] = {}
    for pair in pairs:
        given, sep, text = pair.partition("=")
        key = names.get(given, given)
        if not sep or key not in fields:
            raise ConfigError(f"--set takes KEY=VALUE with KEY one of {', '.join(sorted(fields))}; "
                              f"got {pair!r}")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        settings[key] = typed_setting(given, value, text, hints[key])
    return settings


_KINDS = {int: "an integer", float: "a number", bool: "true or false", str: "text"}


def typed_setting(key: str, value: Any, text: str, hint: Any) -> Any:
    """``value`` (parsed from ``text``) checked against the field's annotation ``hint``; a
    mismatch is one ConfigError naming the field, what it takes and what was given."""
    allowed = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) \
        else (hint,)
    if value is None and type(None) in allowed:
        return None
    nested = [kind for kind in allowed if dataclasses.is_dataclass(kind)]
    if nested:
        if not isinstance(value, dict):
            raise ConfigError(f"--set {key} must be a JSON object of {nested[0].__name__} "
                              f"fields, got {text!r}")
        return from_json(nested[0], value)
    if str in allowed:
        return text
    for kind in (bool, int, float):
        if kind in allowed and isinstance(value, kind) and (kind is bool
                                                            or not isinstance(value, bool)):
            return value
    if float in allowed and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    known = [_KINDS[k] for k in allowed if k in _KINDS]
    if not known:  # tuples, nested configs: the config's own checks judge them
        return value
    raise ConfigError(f"--set {key} must be {' or '.join(known)}, got {text!r}")
