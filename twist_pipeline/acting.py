"""Everything that acts in the simulator, for collection and evaluation alike, behind one
interface: the teacher on privileged state (the oracle; while it trains, the collector's
explorer, with noise and random pushes), a distilled student bundle on images (rendering its
own view where a rollout gives it none), the reference agents (doing nothing, acting at
random), scripted functions of the step, and any policy of the Gymnasium observations.
Each agent is also a rollout policy of the privileged step (``agent(step)``, what
:func:`twist_sim.rollout.record_episode` calls); :func:`load_agent` turns what a user names
into one of them."""

from __future__ import annotations

import importlib
import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from twist_data.errors import TwistError
from twist_models.agent import Agent, AgentState
from twist_models.checkpoint import read_checkpoint
from twist_models.rssm import require_posterior_read
from twist_models.teacher import Teacher, teacher_from_checkpoint
from twist_sim.render import DRRenderer
from twist_sim.tasks import Step, TaskEnv


class AgentError(TwistError):
    """An agent that cannot be loaded or made: an unknown reference, a policy that does not
    import, a checkpoint of another kind."""


class EvalAgent(Protocol):
    """What :func:`evaluate` drives."""

    uses_images: bool
    action_repeat: int | None
    """Simulator steps per agent step it was trained at (None: any)."""

    def reset(self) -> None: ...

    def act(self, step: Step, image: np.ndarray | None) -> np.ndarray: ...


def posterior_draws(stoch: int, posterior: str) -> tuple[int, ...] | None:
    """The shape of the uniform draws one acting step takes from torch's stream, for ``stoch``
    latent variables read from the posterior as ``posterior`` says (None: no draws)."""
    return (1, stoch, 1) if posterior == "sample" else None


class RandomPushes:
    """Random shoves of one episode: on each step without a push under way one starts with
    probability 1 / ``every``, lasts 1..``longest`` steps (uniform) and holds one action
    drawn uniform in [-1, 1]^A. Seeded, so an episode's pushes are reproducible."""

    def __init__(self, every: int, longest: int, action_dim: int, seed: int) -> None:
        self.every, self.longest, self.action_dim = every, longest, action_dim
        self.rng = np.random.default_rng(seed)
        self.left = 0
        self.action = np.zeros(action_dim, np.float32)

    def __call__(self) -> np.ndarray | None:
        """This step's push action, or None when the policy acts."""
        if self.left == 0 and self.rng.random() < 1.0 / self.every:
            self.left = int(self.rng.integers(1, self.longest + 1))
            self.action = self.rng.uniform(-1.0, 1.0, self.action_dim).astype(np.float32)
        if self.left == 0:
            return None
        self.left -= 1
        return self.action


class StateAgent:
    """The teacher acting on privileged state: the oracle (its actor's mode), or, while it
    trains, the collector's explorer (its actor sampled, with noise and random pushes)."""

    uses_images = False

    def __init__(self, teacher: Teacher, task: str | None, device: str = "cpu",
                 action_repeat: int | None = None, posterior: str = "sample",
                 explore: bool = False, noise: float = 0.0,
                 pushes: RandomPushes | None = None) -> None:
        """``posterior``: how the teacher takes z from its posterior; ``sample`` as it was
        trained (``twist-eval``'s oracle always samples: it is the normaliser). ``explore``
        samples the actor instead of taking its mode; ``noise`` adds Gaussian noise of that
        std to each action (clipped to [-1, 1]); while one of ``pushes`` is under way, the
        push's action is taken instead. The filter always sees the action taken."""
        require_posterior_read(posterior)
        self.posterior = posterior
        self.teacher = teacher.to_device(device)
        self.action_dim = teacher.config.world_model.action_dim
        self.device = device
        self.task = task
        self.action_repeat = action_repeat
        self.explore, self.noise, self.pushes = explore, noise, pushes
        self.reset()

    def reset(self) -> None:
        self.reset_batch(1)

    def act(self, step: Step, image: np.ndarray | None) -> np.ndarray:
        return self.act_batch([step], None, None)[0]

    def __call__(self, step: Step) -> np.ndarray:
        """The agent as a rollout policy of the privileged step."""
        return self.act(step, None)

    @property
    def batchable(self) -> bool:
        """Whether :meth:`act_batch` reproduces :meth:`act`'s draws: not for a teacher that
        reads its state through fresh noise (drawn inside the model, per call)."""
        return not self.teacher.config.world_model.state_noise

    @property
    def draw_shape(self) -> tuple[int, ...] | None:
        """The shape of the draws one :meth:`act` takes from torch's stream (None: none)."""
        return posterior_draws(self.teacher.config.world_model.rssm.stoch, self.posterior)

    def reset_batch(self, n: int) -> None:
        self._latent = None
        self._previous = torch.zeros(n, self.action_dim, device=self.device)

    def act_batch(self, steps: Sequence[Step], images: np.ndarray | None,
                  uniform: torch.Tensor | None) -> np.ndarray:
        """One step of ``len(steps)`` episodes at once, ``uniform`` [N, S, 1] the posterior's
        draws of each -> actions [N, A]."""
        state = torch.as_tensor(np.stack([s.state for s in steps]), device=self.device).float()
        # Only a first step needs is_first's masking (~100 us of the ~1 ms acting step); a
        # check inside the RSSM would cost training a device sync per step instead.
        first = (torch.tensor([s.is_first for s in steps], device=self.device)
                 if steps[0].is_first else None)
        action, self._latent = self.teacher.policy(
            state, self._latent, self._previous, first, explore=self.explore,
            read=self.posterior, uniform=None if uniform is None else uniform.to(self.device))
        if self.noise:
            action = (action + self.noise * torch.randn_like(action)).clamp(-1.0, 1.0)
        push = self.pushes() if self.pushes is not None else None
        if push is not None:
            action = torch.as_tensor(push, device=self.device).expand_as(action).clone()
        self._previous = action
        return action.cpu().numpy()


class ImageAgent:
    """A distilled student bundle acting on one rendered view."""

    uses_images = True

    def __init__(self, agent: Agent, posterior: str = "sample") -> None:
        self.agent = agent
        self.posterior = posterior
        self.task = self.agent.info.get("task")
        self.image_size = self.agent.info.get("image_size")
        self.supersample = self.agent.info.get("supersample")
        self.action_repeat = self.agent.info.get("action_repeat")
        self._state: AgentState | None = None

    def reset(self) -> None:
        self._state = None

    def act(self, step: Step, image: np.ndarray | None) -> np.ndarray:
        action, self._state = self.agent.act(image, self._state, posterior=self.posterior)
        return action

    def rendering(self, renderer: DRRenderer, seed: int) -> Callable[[Step], np.ndarray]:
        """The agent as a rollout policy of the privileged step for one episode: it renders
        each step itself (one view under ``renderer``'s DR, drawn from ``seed``) and acts on
        that image (the collector's episodes of a distilled student)."""
        sampler = renderer.sampler(seed)
        sampler.begin_episode(seed)
        self.reset()

        def act(step: Step) -> np.ndarray:
            return self.act(step, renderer.render(step.physics, sampler.sample())[0])

        return act

    batchable = True

    @property
    def draw_shape(self) -> tuple[int, ...] | None:
        """The shape of the draws one :meth:`act` takes from torch's stream (None: none)."""
        return posterior_draws(self.agent.config.student.rssm.stoch, self.posterior)

    def reset_batch(self, n: int) -> None:
        self._state = None

    def act_batch(self, steps: Sequence[Step], images: np.ndarray | None,
                  uniform: torch.Tensor | None) -> np.ndarray:
        """One step of ``len(steps)`` episodes at once on ``images`` [N, H, W, 3], ``uniform``
        [N, S, 1] the posterior's draws of each -> actions [N, A]."""
        action, self._state = self.agent.act(
            images, self._state, posterior=self.posterior,
            uniform=None if uniform is None else uniform.to(self.agent.device))
        return action


class ScriptedAgent:
    """A function of the privileged step (tests, the reference agents)."""

    uses_images = False

    def __init__(self, policy: Callable[[Step], np.ndarray], task: str | None = None,
                 action_repeat: int | None = None) -> None:
        self.policy, self.task, self.action_repeat = policy, task, action_repeat

    def reset(self) -> None:
        pass

    def act(self, step: Step, image: np.ndarray | None) -> np.ndarray:
        return self.policy(step)


class PolicyAgent:
    """Any policy of the observations the Gymnasium environments give
    (:mod:`twist_sim.gym_env`): ``policy({"image": uint8 [H, W, 3], "state": [S]})`` -> action
    [A], with only the keys of ``observe``; its ``reset()`` is called at each episode's start
    when it has one. So a policy written against ``gymnasium.make("twist/...")`` is scored by
    :func:`run_evaluation` on the same scenes and seeds as the toolkit's agents."""

    action_repeat = None

    def __init__(self, policy: Callable[[dict[str, np.ndarray]], np.ndarray],
                 observe: tuple[str, ...] = ("image", "state"), task: str | None = None) -> None:
        self.policy, self.observe, self.task = policy, tuple(observe), task
        self.uses_images = "image" in self.observe

    def reset(self) -> None:
        reset = getattr(self.policy, "reset", None)
        if callable(reset):
            reset()

    def act(self, step: Step, image: np.ndarray | None) -> np.ndarray:
        observation = {"image": image, "state": np.asarray(step.state, np.float32)}
        return self.policy({k: observation[k] for k in self.observe})


#: Agents ``twist-eval --agent NAME`` knows without a file: the floor a trained agent must
#: clear. On cartpole-balance a pole left alone scores ~750, three quarters of a balancing
#: oracle (it starts upright and, undamped, spins through the top), which an
#: oracle-normalised score alone hides.
REFERENCE_AGENTS = {
    "zero": "every action 0 (the agent that does nothing)",
    "random": "actions uniform in [-1, 1], seeded per episode",
}


def reference_agent(kind: str, task: str) -> ScriptedAgent:
    """The reference policy ``kind`` of :data:`REFERENCE_AGENTS`, sized for ``task``."""
    if kind not in REFERENCE_AGENTS:
        raise AgentError(f"unknown reference agent {kind!r}; valid: {', '.join(REFERENCE_AGENTS)}")
    action_dim = TaskEnv(task).action_dim
    if kind == "zero":
        zero = np.zeros(action_dim, np.float32)
        return ScriptedAgent(lambda step: zero, task)
    # torch's stream: evaluate() seeds it per episode, so every re-run draws the same.
    return ScriptedAgent(lambda step: (torch.rand(action_dim) * 2.0 - 1.0).numpy(), task)


def is_reference(spec: str | os.PathLike[str]) -> bool:
    """Whether an agent ``spec`` names a reference agent (a file of that name wins)."""
    return str(spec) in REFERENCE_AGENTS and not Path(spec).exists()


#: ``module:attribute``, a policy of the Gymnasium observations to import.
POLICY_SPEC = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")


def is_policy(spec: str | os.PathLike[str]) -> bool:
    """Whether an agent ``spec`` names an importable policy (a file of that name wins)."""
    return bool(POLICY_SPEC.match(str(spec))) and not Path(spec).exists()


def policy_agent(spec: str) -> PolicyAgent:
    """``module:attribute`` -> the :class:`PolicyAgent` of that callable; it may say what it
    reads (``observe``, default image and state) and its ``task`` as attributes."""
    module_name, _, attribute = spec.partition(":")
    try:
        target: Any = importlib.import_module(module_name)
    except ImportError as exc:
        raise AgentError(f"cannot import module {module_name!r} for the policy {spec!r}: "
                        f"{exc}") from None
    for part in attribute.split("."):
        if not hasattr(target, part):
            raise AgentError(f"module {module_name!r} has no {attribute!r} for the policy "
                            f"{spec!r}")
        target = getattr(target, part)
    if not callable(target):
        raise AgentError(f"the policy {spec!r} is not callable")
    return PolicyAgent(target, tuple(getattr(target, "observe", ("image", "state"))),
                       getattr(target, "task", None))


def load_agent(path: str | os.PathLike[str], device: str = "cpu", task: str | None = None,
               posterior: str = "sample") -> EvalAgent:
    """A teacher checkpoint becomes the state oracle, an agent bundle the image agent (reading
    its posterior as ``posterior`` says), a name from :data:`REFERENCE_AGENTS` that
    reference policy (it needs ``task``), and ``module:attribute`` that imported policy of
    the Gymnasium observations (:class:`PolicyAgent`)."""
    if is_policy(path):
        return policy_agent(str(path))
    if is_reference(path):
        if task is None:
            raise AgentError(f"the reference agent {str(path)!r} needs a task; pass --task or "
                            "a trained agent beside it")
        return reference_agent(str(path), task)
    checkpoint = read_checkpoint(path)
    if checkpoint.kind == "teacher":
        collect = checkpoint.extra.get("collect") or {}
        teacher = teacher_from_checkpoint(checkpoint, source=str(path)).eval()
        return StateAgent(teacher, collect.get("task"), device, collect.get("action_repeat"))
    if checkpoint.kind == "agent":
        return ImageAgent(Agent.from_checkpoint(checkpoint, device), posterior)
    kind = checkpoint.kind
    raise AgentError(f"{str(path)!r} holds a {kind}; evaluate a teacher checkpoint or an "
                    "agent bundle (agent.pt from twist-distil)")


def agent_kind(agent: EvalAgent) -> str:
    """``oracle``, ``reference``, ``policy``, ``student`` or the baseline's kind: the ``kind``
    column."""
    if isinstance(agent, StateAgent):
        return "oracle"
    if isinstance(agent, ScriptedAgent):
        return "reference"
    if isinstance(agent, PolicyAgent):
        return "policy"
    return agent.agent.info.get("baseline", "student")
