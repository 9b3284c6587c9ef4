"""Exception types of the simulator side: a task that is not registered or cannot be, a
physics state that does not fit its task, backgrounds that do not load, rendering with no GL.
Each is a :class:`twist_data.errors.TwistError`, which the commands report in one sentence."""

from __future__ import annotations

from twist_data.errors import TwistError


class UnknownTaskError(TwistError):
    """A task name that is not one of the registered simulated tasks."""


class TaskRegistrationError(TwistError, ValueError):
    """A task cannot be registered: a name taken already, a spec that does not describe a
    usable task, or a task module that does not import."""


class PhysicsStateError(TwistError):
    """A physics state vector that does not fit the task (wrong length, not finite)."""


class BackgroundError(TwistError):
    """Background images cannot be loaded (missing, empty or unreadable directory)."""


class RenderUnavailableError(TwistError):
    """No OpenGL context could be created for offscreen rendering."""


def error_type(name: str) -> type[TwistError] | None:
    """The toolkit's exception class called ``name`` (the simulator's or the dataset's), or
    None: how a child process's failure is raised again as the parent's own type."""
    from twist_data import errors as dataset_errors

    for module in (globals(), vars(dataset_errors)):
        kind = module.get(name)
        if isinstance(kind, type) and issubclass(kind, TwistError):
            return kind
    return None
