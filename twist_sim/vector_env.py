"""Several evaluation environments stepped together, in this process or in worker processes.

An evaluation that steps N episodes together (``twist-eval --batch N``) makes one batched
policy call per step, but simulating and rendering N environments one after another stays
in the calling process. :class:`EnvWorkers` spreads the environments over worker processes
so that they step and render in parallel while the caller waits for all of them, then acts
for all of them in one call: on a many-core GPU host, where the policy call is cheap, the
simulation is what is left.

Both classes answer the same two calls, :meth:`reset` and :meth:`step`, with each slot's
:class:`~twist_sim.tasks.Step` and its one rendered view (None when not rendering). A slot is
one environment, its DR sampler (seeded per episode by ``begin_episode``) and, in a worker,
a renderer shared with the worker's other slots; the same episode seeds and actions give the
same steps and pixels in either class (tested), so :class:`LocalEnvs` is the reference.

Workers are started as ``python -m twist_sim.vector_env`` over a socket pair, as the
collector's render process is (:mod:`twist_sim.render_process` says why not
``multiprocessing``), and exit when their socket closes.
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
from collections.abc import Sequence
from multiprocessing.connection import Connection, wait
from typing import Any

import numpy as np

from twist_data.errors import ConfigError, TwistError
from twist_sim.errors import error_type
from twist_sim.randomisation import DRConfig
from twist_sim.tasks import Step, TaskEnv

#: (step, its view [H, W, 3] uint8 or None) of one slot.
Observed = tuple[Step, "np.ndarray | None"]


class EnvWorkerError(TwistError):
    """An environment worker failed or exited."""


class LocalEnvs:
    """``slots`` environments of ``task`` and their DR samplers, in this process.

    ``render``: draw each step's view (one, under ``dr``). The views of all the slots stepped
    together are drawn in one framebuffer and read back at once (one wait for the GPU), slot i
    in place ``places[i]`` (default i), so that a slot's pixels do not depend on which other
    slots are stepped with it, nor on the process (:class:`EnvWorkers` gives each worker's
    slots their places in the whole batch)."""

    def __init__(self, task: str, slots: int, dr: DRConfig, image_size: int = 64,
                 supersample: int = 1, action_repeat: int = 2, seed: int = 0,
                 max_steps: int | None = None, render: bool = True,
                 places: Sequence[int] | None = None) -> None:
        from twist_sim.render import DRRenderer

        self.places = list(range(slots)) if places is None else [int(p) for p in places]
        if len(self.places) != slots:
            raise ConfigError(f"LocalEnvs needs one place per slot, got {len(self.places)} "
                              f"for {slots} slots")
        self.envs = [TaskEnv(task, action_repeat, seed=seed, max_steps=max_steps)
                     for _ in range(slots)]
        self.renderer = DRRenderer(task, dr, image_size, views=1, supersample=supersample,
                                   states=max(self.places) + 1)
        self.samplers = [self.renderer.sampler(seed) for _ in range(slots)]
        self.slots, self.render = slots, render
        self.settings = dict(task=task, dr=dr, image_size=image_size, supersample=supersample,
                             action_repeat=action_repeat, max_steps=max_steps)

    def _observe(self, slots: Sequence[int], steps: list[Step]) -> list[Observed]:
        if not self.render or not slots:
            return [(step, None) for step in steps]
        images = self.renderer.render_states(
            [step.physics for step in steps], [self.samplers[slot].sample() for slot in slots],
            places=[self.places[slot] for slot in slots])
        return [(step, image[0]) for step, image in zip(steps, images, strict=True)]

    def reset(self, seeds: Sequence[int]) -> list[Observed]:
        """Start an episode in slots 0..len(seeds)-1, slot i with episode seed ``seeds[i]``."""
        slots = range(len(seeds))
        return self._observe(slots, [self.envs[slot].reset(
            seed=s, dynamics=self.samplers[slot].begin_episode(s)) for slot, s in zip(
                slots, seeds, strict=True)])

    def step(self, slots: Sequence[int], actions: Sequence[np.ndarray]) -> list[Observed]:
        """Step each of ``slots`` with its action (in [-1, 1]); returns their observations."""
        return self._observe(slots, [self.envs[slot].step(action)
                                     for slot, action in zip(slots, actions, strict=True)])

    def close(self) -> None:
        self.renderer.close()

    def __enter__(self) -> LocalEnvs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _serve(conn: Connection) -> None:
    """A worker: one :class:`LocalEnvs` answering the parent's socket until it closes."""
    try:
        kwargs = conn.recv()
        kwargs["dr"] = DRConfig.from_json(kwargs["dr"])
        envs = LocalEnvs(**kwargs)
    except Exception as exc:  # reported to the parent, which raises it there
        with contextlib.suppress(OSError):  # unless it has already gone
            conn.send(("error", (type(exc).__name__, str(exc))))
        return
    conn.send(("ready", None))
    with envs:
        while True:
            try:
                command, payload = conn.recv()
            except (EOFError, OSError):  # the parent is gone
                return
            try:
                if command == "reset":
                    reply: Any = envs.reset(payload)
                elif command == "step":
                    reply = envs.step(*payload)
                else:
                    return
            except Exception as exc:
                conn.send(("error", (type(exc).__name__, str(exc))))
                continue
            conn.send(("ok", reply))


class EnvWorkers:
    """``slots`` environments spread over ``workers`` processes, slot i in worker
    i mod ``workers``; the same calls and answers as :class:`LocalEnvs`."""

    def __init__(self, task: str, slots: int, workers: int, dr: DRConfig,
                 image_size: int = 64, supersample: int = 1, action_repeat: int = 2,
                 seed: int = 0, max_steps: int | None = None, render: bool = True) -> None:
        if workers < 1:
            raise ConfigError(f"workers must be >= 1, got {workers}")
        self.workers = min(workers, slots)
        self.slots, self.render = slots, render
        self.settings = dict(task=task, dr=dr, image_size=image_size, supersample=supersample,
                             action_repeat=action_repeat, max_steps=max_steps)
        self._conns: list[Connection] = []
        self._processes: list[subprocess.Popen] = []
        for worker in range(self.workers):
            ours, theirs = socket.socketpair()
            self._processes.append(subprocess.Popen(
                [sys.executable, "-m", "twist_sim.vector_env", str(theirs.fileno())],
                pass_fds=[theirs.fileno()]))
            theirs.close()
            self._conns.append(Connection(ours.detach()))
            own = list(range(worker, slots, self.workers))
            self._conns[-1].send({**self.settings, "dr": dr.to_json(), "slots": len(own),
                                  "places": own, "seed": seed, "render": render})
        try:
            self._gather(list(range(self.workers)))
        except EnvWorkerError:
            self.close()
            raise

    def _gather(self, workers: list[int]) -> list[Any]:
        """Every asked worker's reply, in the order of ``workers``; a failure is raised as
        the worker's own error type where it is one of ours."""
        replies = []
        for worker in workers:
            try:
                status, payload = self._conns[worker].recv()
            except (EOFError, OSError):
                code = self._processes[worker].poll()
                raise EnvWorkerError(f"environment worker {worker} exited (exit code "
                                     f"{code})") from None
            if status == "error":
                name, message = payload
                kind = error_type(name)
                if kind is not None:
                    raise kind(message)
                raise EnvWorkerError(f"environment worker {worker} failed: {name}: {message}")
            replies.append(payload)
        return replies

    def reset(self, seeds: Sequence[int]) -> list[Observed]:
        """As :meth:`LocalEnvs.reset`: slot i gets episode seed ``seeds[i]``."""
        n = self.workers
        asked = [w for w in range(n) if w < len(seeds)]
        for worker in asked:
            self._send(worker, ("reset", list(seeds[worker::n])))
        return self._merge(asked, [list(range(w, len(seeds), n)) for w in asked])

    def step(self, slots: Sequence[int], actions: Sequence[np.ndarray]) -> list[Observed]:
        """As :meth:`LocalEnvs.step`: the observations of ``slots``, in their order."""
        n = self.workers
        mine: dict[int, list[int]] = {}
        for k, slot in enumerate(slots):
            mine.setdefault(slot % n, []).append(k)
        asked = sorted(mine)
        for worker in asked:
            self._send(worker, ("step", ([slots[k] // n for k in mine[worker]],
                                         [np.asarray(actions[k]) for k in mine[worker]])))
        by_slot = dict(zip([slots[k] for w in asked for k in mine[w]],
                           [o for part in self._replies(asked) for o in part], strict=True))
        return [by_slot[slot] for slot in slots]

    def _send(self, worker: int, message: tuple[str, Any]) -> None:
        try:
            self._conns[worker].send(message)
        except (BrokenPipeError, OSError):
            raise EnvWorkerError(f"environment worker {worker} exited (exit code "
                                 f"{self._processes[worker].poll()})") from None

    def _replies(self, workers: list[int]) -> list[list[Observed]]:
        wait([self._conns[w] for w in workers])  # all of them work meanwhile
        return self._gather(workers)

    def _merge(self, workers: list[int], slots: list[list[int]]) -> list[Observed]:
        merged: dict[int, Observed] = {}
        for owned, part in zip(slots, self._replies(workers), strict=True):
            merged.update(zip(owned, part, strict=True))
        return [merged[slot] for slot in sorted(merged)]

    def close(self) -> None:
        for conn, process in zip(self._conns, self._processes, strict=True):
            if not conn.closed:
                if process.poll() is None:
                    with contextlib.suppress(OSError):
                        conn.send(("close", None))
                conn.close()
            try:
                process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()

    def __enter__(self) -> EnvWorkers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


if __name__ == "__main__":
    _serve(Connection(int(sys.argv[1])))
