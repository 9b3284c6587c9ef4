"""DR rendering in a child process, overlapped with the caller's physics and policy.

Why a process: on a 2-core machine the collector's loop is physics + acting + rendering, and
rendering (Mesa llvmpipe, ~40% of the loop) needs nothing from the other two but the physics
vector and the DR parameters of each step. A thread would share the GIL with the Python-heavy
physics and policy code (measured: 28 K=2 renders/s in a thread beside a busy Python loop,
638 alone); a spawned process renders on the second core while the first steps the
simulator. Frames are pure functions of (physics, parameters), so they are the same pixels
as :class:`~twist_sim.render.DRRenderer` renders in-process.

Protocol: :meth:`RenderProcess.submit` sends (physics, parameters) down a pipe and returns at
once; :meth:`RenderProcess.gather` waits for every submitted frame and receives them as one
byte block (an episode of 64x64 K=2 frames is ~12 MB, a few milliseconds through a pipe).
The child exits when its pipe closes, so a parent killed with SIGKILL leaves nothing behind.
It is started as ``python -m twist_sim.render_process`` rather than through
``multiprocessing``: spawn would re-import the caller's ``__main__`` (a script without an
``if __name__ == "__main__"`` guard would fail), and fork would copy a parent holding torch
threads and a GL context.
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
from collections.abc import Mapping
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from twist_data.errors import TwistError
from twist_sim.errors import RenderUnavailableError, error_type
from twist_sim.randomisation import DRConfig, DRSampler

_GATHER = "gather"
_CLOSE = "close"


class RenderProcessError(TwistError):
    """The render process failed, or exited, while rendering submitted frames."""


def _serve(conn: Connection) -> None:
    """The child: one DRRenderer answering the parent's pipe until it closes."""
    from twist_sim.render import DRRenderer

    try:
        task, config, image_size, views, supersample = conn.recv()
        renderer = DRRenderer(task, DRConfig.from_json(config), image_size, views, supersample)
    except Exception as exc:  # reported to the parent, which raises it there
        conn.send(("error", (type(exc).__name__, str(exc))))
        return
    bank = renderer.bank
    conn.send(("ready", {"nominal_colours": renderer.nominal_colours,
                         "n_backgrounds": len(bank) if bank is not None else 0,
                         "max_offset": renderer.max_offset,
                         "background_colours": renderer.background_colours,
                         "provenance": renderer.provenance()}))
    frames = np.empty((512, views, image_size, image_size, 3), np.uint8)
    count, error = 0, None
    with renderer:
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):  # the parent is gone
                return
            if message == _CLOSE:
                return
            if message == _GATHER:
                conn.send((count, error))
                if error is None:
                    conn.send_bytes(memoryview(frames[:count]).cast("B"))
                count, error = 0, None
                continue
            if error is not None:
                continue  # skip the rest of a failed batch; gather reports the first error
            physics, params = message
            if count == len(frames):
                frames = np.concatenate([frames, np.empty_like(frames)])
            try:
                renderer.render(physics, params, out=frames[count])
                count += 1
            except Exception as exc:
                error = f"{type(exc).__name__}: {exc}"


class RenderProcess:
    """A :class:`~twist_sim.render.DRRenderer` of ``task`` in a spawned child process.

    Offers the renderer's ``views``, ``image_size``, :meth:`sampler` and :meth:`provenance`,
    plus :meth:`submit` / :meth:`gather` for pipelined rendering. Use as a context manager,
    or call :meth:`close`.
    """

    def __init__(self, task: str, config: DRConfig, image_size: int = 64, views: int = 2,
                 supersample: int = 1) -> None:
        self.config = config
        self.image_size = image_size
        self.views = views
        ours, theirs = socket.socketpair()
        self._process = subprocess.Popen(
            [sys.executable, "-m", "twist_sim.render_process", str(theirs.fileno())],
            pass_fds=[theirs.fileno()])
        theirs.close()
        self._conn = Connection(ours.detach())
        self._pending = 0
        try:
            self._conn.send((task, config.to_json(), image_size, views, supersample))
            status, payload = self._conn.recv()
        except (EOFError, OSError):
            self.close()
            raise RenderUnavailableError(f"the render process for {task!r} exited while "
                                         f"starting (exit code {self._process.poll()})") from None
        if status != "ready":
            self.close()
            name, message = payload
            # The child's own error type when it is one of ours (a bad background folder is
            # a BackgroundError however it is rendered), else "rendering is unavailable".
            kind = error_type(name)
            if kind is not None:
                raise kind(message)
            raise RenderUnavailableError(f"the render process for {task!r} could not start: "
                                         f"{name}: {message}")
        self._info = payload

    def sampler(self, seed: int = 0) -> DRSampler:
        """A parameter sampler matched to the child's bank, nominal colours and K."""
        info = self._info
        return DRSampler(self.config, info["nominal_colours"], self.views, info["n_backgrounds"],
                         info["max_offset"], seed, info["background_colours"])

    def provenance(self, first_view: int = 0) -> dict[str, Any]:
        """As :meth:`DRRenderer.provenance`."""
        block = dict(self._info["provenance"])
        block["views"] = [first_view, first_view + self.views]
        return block

    def submit(self, physics: np.ndarray, params: Mapping[str, np.ndarray]) -> None:
        """Queue the K views of ``physics`` under ``params``; returns before they are drawn."""
        try:
            self._conn.send((np.asarray(physics), dict(params)))
        except (BrokenPipeError, OSError):
            raise self._exited() from None
        self._pending += 1

    def gather(self) -> np.ndarray:
        """Every frame submitted since the last gather, in order: [T, K, H, W, 3] uint8."""
        try:
            self._conn.send(_GATHER)
            count, error = self._conn.recv()
            if error is not None:
                self._pending = 0
                raise RenderProcessError(f"rendering a submitted frame failed: {error}")
            side = self.image_size
            frames = np.empty((count, self.views, side, side, 3), np.uint8)
            if count:
                self._conn.recv_bytes_into(memoryview(frames).cast("B"))
        except (EOFError, BrokenPipeError, ConnectionResetError):
            raise self._exited() from None
        if count != self._pending:
            raise RenderProcessError(f"the render process returned {count} frames for "
                                     f"{self._pending} submitted")
        self._pending = 0
        return frames

    def _exited(self) -> RenderProcessError:
        try:
            code = self._process.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            code = None
        return RenderProcessError(f"the render process exited (exit code {code}) with "
                                  f"{self._pending} frames pending")

    def close(self) -> None:
        if self._conn.closed:
            return
        if self._process.poll() is None:
            with contextlib.suppress(OSError):
                self._conn.send(_CLOSE)
            try:
                self._process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._conn.close()

    def __enter__(self) -> RenderProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


if __name__ == "__main__":
    _serve(Connection(int(sys.argv[1])))
