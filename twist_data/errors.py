"""Exception types of the toolkit (the simulator's own are in ``twist_sim.errors``). Every
message is one sentence naming the problem and the value."""

from __future__ import annotations

import importlib
from typing import Any


class TwistError(Exception):
    """Base class of every error the toolkit raises on bad input or bad data."""


class NotADatasetError(TwistError):
    """The path is not a twist dataset or shard."""


class FormatVersionError(TwistError):
    """The store was written in a format version this library cannot read."""


class SchemaMismatchError(TwistError):
    """Shards of one dataset, or an episode and its shard, disagree on the schema."""


class InvalidEpisodeError(TwistError):
    """An episode handed to the writer breaks the format's rules (shapes, dtypes, flags, values)."""


class DatasetCorruptError(TwistError):
    """Stored data is missing, truncated or inconsistent."""


class SamplerConfigError(TwistError):
    """A sampler or reader request cannot be served by this dataset (window too long, bad view)."""


class ImagesStrippedError(TwistError):
    """A dataset stripped of its images (``twist-data strip``) was given to something that
    reads images."""


class PairsMissingError(TwistError):
    """A dataset without frame pairs (``data/pair_image``) was given to something that reads
    them."""


class ShardLockedError(TwistError):
    """Another process is already writing this shard."""


class ConfigError(TwistError, ValueError):
    """A configuration value is out of range or inconsistent with another one."""


class MissingExtraError(TwistError, ImportError):
    """An optional integration was asked for without its extra installed."""


def import_extra(module: str, extra: str, reason: str) -> Any:
    """``module`` imported, or a :class:`MissingExtraError` saying that ``reason`` (e.g.
    "exporting to Minari needs") the ``extra`` and the command that installs it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtraError(f"{reason} the {extra} extra: "
                                f"pip install 'twist[{extra}]'") from None
