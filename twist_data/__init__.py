"""twist_data: the matching dataset D of TWIST as a versioned Zarr artifact.

Public entry points: :class:`ShardWriter` to append episodes, :func:`open_dataset` to read,
:class:`WindowSampler` / :class:`WindowDataset` for training windows, :func:`verify_dataset`,
and :func:`write_synthetic_dataset` for fixtures and demos.
"""

__version__ = "0.1.0"
