"""twist_data: the matching dataset D of TWIST as a versioned Zarr artifact.

Public entry points: :class:`ShardWriter` to append episodes, :func:`open_dataset` to read,
:class:`WindowSampler` / :class:`WindowDataset` for training windows, :func:`verify_dataset`,
and :func:`write_synthetic_dataset` for fixtures and demos.
"""

import os

# Offscreen rendering must work on headless machines, and MuJoCo picks its GL backend when it is
# first imported: default to EGL unless the user chose a backend.
os.environ.setdefault("MUJOCO_GL", "egl")

__version__ = "0.1.0"
