"""One episode of D on a timeline in the rerun viewer (``pip install twist[viz]``).

Every step t of the episode is logged at ``step = t`` of a ``step`` timeline:

* ``views/<k>``: the K randomised renders (images);
* ``state/<name>``: the privileged state, one series per component, named by D's
  ``state_layout`` (``state/<name>`` holds the block's components; ``state`` when unnamed);
* ``action``, ``reward``: D's row t (the action that *led to* step t, the reward received on
  arriving there);
* ``flags``: ``is_first``, ``is_last``, ``is_terminal`` as 0/1 series;
* ``dr/<name>/view<k>``: every per-step DR parameter of each view;
* ``episode`` (static): the provenance (seed, policy, teacher updates, per-episode DR).

:func:`log_episode` writes to a ``.rrd`` file (open it later with ``rerun FILE.rrd``) or to a
viewer it spawns.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from twist_data.errors import TwistError, import_extra
from twist_data.reader import MatchingDataset, open_dataset


class ViewerError(TwistError):
    """An episode could not be shown or saved."""


def _rerun() -> Any:
    return import_extra("rerun", "viz", "the timeline viewer needs")


def state_series(data: MatchingDataset) -> list[tuple[str, slice]]:
    """(entity path, columns of the state vector) per named block of D's state."""
    layout = data.spec.state_layout or (("", data.spec.state_dim),)
    series, start = [], 0
    for name, size in layout:
        series.append((f"state/{name}" if name else "state", slice(start, start + size)))
        start += size
    return series


def log_episode(dataset_path: str | os.PathLike[str], episode: int,
                save: str | os.PathLike[str] | None = None) -> Path | None:
    """Log episode ``episode`` (global index; negative counts from the end) of the dataset at
    ``dataset_path``: into the file ``save`` (``.rrd``, written aside and renamed when
    complete; returns its path), or else to a rerun viewer spawned for it."""
    rr = _rerun()
    data = open_dataset(dataset_path)
    n = data.n_episodes
    if not -n <= episode < n:
        raise ViewerError(f"dataset has {n} episodes; index {episode} is out of range")
    index = episode % n
    out = None if save is None else Path(save)
    if out is not None and out.suffix != ".rrd":
        raise ViewerError(f"{out} must end in .rrd (rerun's recording file)")
    if out is not None and out.is_dir():
        raise ViewerError(f"{out} is a folder; give the path of the .rrd file to write")
    if out is None and sys.platform.startswith("linux") and not (
            os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ViewerError("no display to open the rerun viewer on (DISPLAY and "
                          "WAYLAND_DISPLAY are unset); pass --save FILE.rrd and open the file "
                          "with `rerun FILE.rrd` where there is one")
    recording = rr.RecordingStream("twist", recording_id=f"{data.path.name}-episode-{index}")
    partial = None
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        partial = out.with_name(f".{out.name}.partial")
        recording.save(str(partial))
    else:
        recording.spawn()
    try:
        _log(rr, recording, data, index)
        recording.flush()
        recording.disconnect()
        if partial is not None and out is not None:
            os.replace(partial, out)
    except RuntimeError as exc:  # rerun's sinks report a failed viewer or file this way
        raise ViewerError(f"rerun could not take the recording: {exc}") from None
    finally:
        if partial is not None:
            partial.unlink(missing_ok=True)
    return out


def _log(rr: Any, recording: Any, data: MatchingDataset, index: int) -> None:
    episode, info = data.episode(index), data.episode_info(index)
    provenance = {"dataset": str(data.path), "episode": index, "task": data.spec.task,
                  "seed": int(info.seed), "policy": info.policy,
                  "teacher_step": int(info.teacher_step), "env_step": int(info.env_step),
                  "dr": {k: v.item() if isinstance(v, np.generic) else v
                         for k, v in info.dr.items()}}
    recording.log("episode", rr.TextDocument(json.dumps(provenance, indent=2),
                                             media_type="text/markdown"), static=True)
    series = state_series(data)
    flags = np.stack([episode.is_first, episode.is_last, episode.is_terminal], 1)
    for t in range(len(episode)):
        recording.set_time("step", sequence=t)
        for k in range(episode.image.shape[1]):
            recording.log(f"views/{k}", rr.Image(episode.image[t, k]))
        for path, columns in series:
            recording.log(path, rr.Scalars(episode.state[t, columns].astype(np.float64)))
        recording.log("action", rr.Scalars(episode.action[t].astype(np.float64)))
        recording.log("reward", rr.Scalars([float(episode.reward[t])]))
        recording.log("flags", rr.Scalars(flags[t].astype(np.float64)))
        for name, values in episode.dr.items():
            for k in range(values.shape[1]):
                recording.log(f"dr/{name}/view{k}",
                              rr.Scalars(np.ravel(values[t, k]).astype(np.float64)))


__all__ = ["ViewerError", "log_episode", "state_series"]
