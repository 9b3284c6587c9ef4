"""Typed, frozen configurations of the world models and the actor-critic, with named presets.

Defaults follow DreamerV2's ``dmc`` settings (``danijar/dreamerv2``, ``configs.yaml``) and the
TWIST paper (state encoder/decoder MLPs of 3 x 512 ELU). Every config is saved inside every
checkpoint, and a checkpoint is only loaded into a model built from an equal config.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

from twist_data.errors import ConfigError

T = TypeVar("T")


def require_positive(obj: object, *names: str) -> None:
    """Raise ConfigError naming the first field of ``obj`` among ``names`` that is not > 0."""
    for name in names:
        value = getattr(obj, name)
        if not value > 0:
            raise ConfigError(f"{type(obj).__name__}.{name} must be > 0, got {value}")


def require_non_negative(obj: object, *names: str) -> None:
    """Raise ConfigError naming the first field of ``obj`` among ``names`` that is < 0."""
    for name in names:
        value = getattr(obj, name)
        if value < 0:
            raise ConfigError(f"{type(obj).__name__}.{name} must be >= 0, got {value}")


def require_choice(obj: object, name: str, choices: tuple[str, ...]) -> None:
    """Raise ConfigError naming field ``name`` of ``obj`` unless its value is in ``choices``."""
    value = getattr(obj, name)
    if value not in choices:
        raise ConfigError(f"{name} must be one of {', '.join(choices)}, got {value!r}")


@dataclass(frozen=True)
class RSSMConfig:
    """Recurrent state-space model sizes and KL settings."""

    deter: int = 200
    """Size of the deterministic GRU state h_t."""
    hidden: int = 200
    """Width of the layers around the GRU and of the prior/posterior heads."""
    stoch: int = 32
    """Number of categorical latent variables in z_t."""
    classes: int = 32
    """Classes per categorical variable."""
    kl_balance: float = 0.8
    """Weight of the prior-side term in KL balancing (DreamerV2: 0.8)."""
    free_nats: float = 1.0
    """KL values below this are not penalised (applied to the batch mean, as DreamerV2)."""

    def __post_init__(self) -> None:
        require_positive(self, "deter", "hidden", "stoch", "classes")
        if not 0.0 <= self.kl_balance <= 1.0 or self.free_nats < 0:
            raise ConfigError(f"kl_balance must be in [0, 1] and free_nats >= 0, got "
                              f"{self.kl_balance} and {self.free_nats}")

    @property
    def feature_dim(self) -> int:
        """Size of the model state feature [h_t, flatten(z_t)] the heads and actor read."""
        return self.deter + self.stoch * self.classes


@dataclass(frozen=True)
class MLPConfig:
    """A multilayer perceptron with ELU activations."""

    layers: int = 4
    """Number of hidden layers."""
    units: int = 400
    """Units per hidden layer."""

    def __post_init__(self) -> None:
        require_positive(self, "layers", "units")


CNN_NORMS = ("none", "layer")


@dataclass(frozen=True)
class CNNConfig:
    """DreamerV2's convolutional image encoder/decoder for 64x64x3 images."""

    #: Removed switches and the value that meant "off" (:func:`removed_fields`): a first
    #: convolution over 4x4 patches and a keypoint head read no more per minute
    #: (docs/findings.md).
    REMOVED: ClassVar[dict[str, Any]] = {"first_stride": 2, "pool": "flatten"}

    depth: int = 48
    """Channels of the first convolution; doubled at every layer."""
    encoder_kernels: tuple[int, ...] = (4, 4, 4, 4)
    """Kernel sizes of the stride-2 valid convolutions (64 -> 31 -> 14 -> 6 -> 2)."""
    decoder_kernels: tuple[int, ...] = (5, 5, 6, 6)
    """Kernel sizes of the stride-2 transposed convolutions (1 -> 5 -> 13 -> 30 -> 64)."""
    image_size: int = 64
    """Side of the square input images."""
    norm: str = "none"
    """Normalisation between each encoder convolution and its activation: ``none``
    (DreamerV2's CNN) or ``layer`` (over each image's channels and pixels, as DreamerV3):
    under DR it learns thin features such as cartpole's pole many times faster."""
    def __post_init__(self) -> None:
        object.__setattr__(self, "encoder_kernels", tuple(self.encoder_kernels))
        object.__setattr__(self, "decoder_kernels", tuple(self.decoder_kernels))
        require_positive(self, "depth", "image_size")
        require_choice(self, "norm", CNN_NORMS)
        if not self.encoder_kernels:
            raise ConfigError("encoder_kernels must name at least one convolution, got ()")
        if self.encoder_map_sizes()[-1] < 1:
            raise ConfigError(f"image size {self.image_size} is too small for kernels "
                              f"{self.encoder_kernels}: no pixel is left after the last")

    def encoder_strides(self) -> tuple[int, ...]:
        """Each encoder convolution's stride: 2."""
        return (2,) * len(self.encoder_kernels)

    def encoder_map_sizes(self) -> list[int]:
        """The side of each encoder convolution's output map (valid convolutions)."""
        sizes, size = [], self.image_size
        for kernel, stride in zip(self.encoder_kernels, self.encoder_strides(), strict=True):
            size = (size - kernel) // stride + 1
            sizes.append(size)
        return sizes


ACTOR_GRADS = ("dynamics", "reinforce")
ACTOR_DISTS = ("trunc_normal", "normal")
CRITIC_HEADS = ("mse", "twohot")
#: Arithmetic settings of the networks a training step runs: ``float32``; ``bfloat16``
#: (autocast: weights, optimiser state and what autocast keeps in float32 stay float32);
#: ``auto``: bfloat16 where the device computes it natively, float32 elsewhere.
PRECISIONS = ("float32", "bfloat16", "auto")


@dataclass(frozen=True)
class ActorCriticConfig:
    """Behaviour learning in imagination."""

    horizon: int = 15
    """Imagination horizon H."""
    discount: float = 0.99
    """gamma."""
    lambda_: float = 0.95
    """lambda of the lambda-returns."""
    actor: MLPConfig = field(default_factory=MLPConfig)
    """Actor network."""
    critic: MLPConfig = field(default_factory=MLPConfig)
    """Critic network."""
    actor_dist: str = "trunc_normal"
    """The actor's distribution over actions in [-1, 1]: ``trunc_normal`` (DreamerV2: a
    normal truncated to the box, std in [min_std, 2 + min_std]) or ``normal`` (the first
    DreamerV3: an untruncated normal about tanh of the mean, std in [min_std, max_std] and
    ~0.9 at initialisation, its sample clipped to the box with the gradient passed straight
    through): a truncated actor whose mean sits at a bound keeps no gradient to leave it."""
    min_std: float = 0.1
    """Minimum standard deviation of the actor."""
    max_std: float = 1.0
    """Maximum standard deviation of the ``normal`` actor."""
    entropy: float = 1e-4
    """Weight of the actor's entropy bonus."""
    slow_target_every: int = 100
    """Critic updates between copies of the critic into its slow target."""
    actor_lr: float = 8e-5
    """Adam learning rate of the actor."""
    critic_lr: float = 8e-5
    """Adam learning rate of the critic."""
    imag_starts: int = 0
    """Posterior states (drawn at random from the batch) that start imagination; 0 = all B*L,
    as DreamerV2. Imagination is ~85% of a CPU teacher update, so CPU presets start from fewer."""
    actor_grad: str = "dynamics"
    """``dynamics``: backpropagate returns through the world model (DreamerV2 on DMC);
    ``reinforce``: score-function gradient with the critic as baseline (DreamerV3)."""
    return_norm: bool = False
    """Divide the actor's objective by max(1, EMA of the 5-95% range of returns) (DreamerV3),
    which keeps the actor's step size independent of the task's reward scale."""
    precision: str = "float32"
    """Arithmetic of the imagined rollouts and of the heads, actor and critic read along them:
    ``float32`` (DreamerV2), ``bfloat16`` (autocast; weights, the GRU's state h, latent
    logits, actions, returns and losses stay float32) or ``auto`` (bfloat16 where the device
    computes it natively: :func:`twist_models.device.resolve_precision`)."""
    critic_head: str = "mse"
    """``mse``: the critic regresses returns (DreamerV2); ``twohot``: a categorical over 255
    symlog-spaced bins trained on two-hot targets (DreamerV3), whose output need not grow to
    the return's scale (~100 on DMC at gamma 0.99) one small Adam step at a time."""

    def __post_init__(self) -> None:
        require_positive(self, "horizon", "slow_target_every", "actor_lr", "critic_lr", "min_std")
        require_choice(self, "critic_head", CRITIC_HEADS)
        require_choice(self, "actor_grad", ACTOR_GRADS)
        require_choice(self, "actor_dist", ACTOR_DISTS)
        if self.actor_dist == "normal" and not self.max_std > self.min_std:
            raise ConfigError(f"max_std must exceed min_std ({self.min_std}) for the normal "
                              f"actor, got {self.max_std}")
        require_choice(self, "precision", PRECISIONS)
        if self.imag_starts < 0:
            raise ConfigError(f"imag_starts must be >= 0 (0 = every state), got {self.imag_starts}")
        if not 0 < self.discount <= 1 or not 0 <= self.lambda_ <= 1:
            raise ConfigError(f"discount must be in (0, 1] and lambda_ in [0, 1], got "
                              f"{self.discount} and {self.lambda_}")


@dataclass(frozen=True)
class OptimConfig:
    """Adam settings shared by all optimisers (learning rates live with each model)."""

    eps: float = 1e-5
    """Adam epsilon."""
    grad_clip: float = 100.0
    """Global gradient-norm clip per optimiser."""
    weight_decay: float = 1e-6
    """Decoupled weight decay (AdamW), as DreamerV2."""

    def __post_init__(self) -> None:
        require_positive(self, "eps", "grad_clip")


@dataclass(frozen=True)
class WorldModelConfig:
    """A world model: encoder, RSSM, decoder and reward (and optional discount) heads."""

    obs: str = "state"
    """What the encoder reads: ``state`` (teacher) or ``image`` (student)."""
    state_dim: int = 5
    """Length of the privileged state vector (``state`` models)."""
    action_dim: int = 1
    """Length of the action vector."""
    rssm: RSSMConfig = field(default_factory=RSSMConfig)
    """RSSM sizes."""
    state_mlp: MLPConfig = field(default_factory=lambda: MLPConfig(layers=3, units=512))
    """State encoder and decoder MLPs (the paper's teacher: 3 x 512)."""
    cnn: CNNConfig = field(default_factory=CNNConfig)
    """Image encoder/decoder (``image`` models)."""
    head: MLPConfig = field(default_factory=MLPConfig)
    """Reward and discount heads."""
    discount_head: bool = False
    """Predict episode continuation (off for DMC, which never terminates)."""
    model_lr: float = 3e-4
    """Adam learning rate of the world model."""
    kl_scale: float = 1.0
    """Weight of the KL term in the world-model loss."""
    reward_scale: float = 1.0
    """Weight of the reward terms, one-step and overshooting (DreamerV2: 1): a task whose best
    rewards are rare in D (walker-walk's walking) may need them fitted beyond their share."""
    recon: str = "obs"
    """What the decoder reconstructs: ``obs`` (what the encoder read) or ``state`` (the
    privileged state from images: the paper's State Recon baseline)."""
    overshoot: int = 0
    """Open-loop steps of the prior, driven by the recorded actions, whose decoded states and
    rewards are also fitted to the recorded ones (0: off, as DreamerV2; state models only)."""
    overshoot_starts: int = 64
    """Posterior states (drawn at random from the batch) that start the open-loop rollouts."""
    state_noise: float = 0.0
    """Std of Gaussian noise added to every privileged-state component each time the state
    encoder reads it: in training, acting and as the distillation target alike, so a state
    teacher perceives the state about as coarsely as a student reads it from images and its
    GRU and actor learn to work from such a belief (``state`` models only; decoder and
    overshooting targets stay exact; 0: exact states, as the paper)."""
    state_hidden: tuple[int, ...] = ()
    """Indices of privileged-state components the state encoder never reads (set to 0 before
    it, in training, acting and as the distillation target), e.g. the velocities: the
    teacher's latent must then infer them from the history of what it reads, as a student
    reading images must; the decoder still reconstructs every component (``state`` models
    only; (): it reads them all, as the paper)."""
    symlog: bool = False
    """Read the state through symlog, sign(x) log(1 + |x|), and reconstruct it in that space
    (DreamerV3's vector inputs): a joint speed of tens then weighs in the model's loss as a
    position does instead of ~100 times more (False: DreamerV2's raw state)."""

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "state_hidden", tuple(int(i) for i in self.state_hidden))
        except (TypeError, ValueError):
            raise ConfigError(f"state_hidden must be a list of state indices, got "
                              f"{self.state_hidden!r}") from None
        if self.obs not in ("state", "image"):
            raise ConfigError(f"obs must be 'state' or 'image', got {self.obs!r}")
        if self.recon not in ("obs", "state"):
            raise ConfigError(f"recon must be 'obs' or 'state', got {self.recon!r}")
        require_positive(self, "action_dim", "model_lr", "overshoot_starts", "reward_scale")
        require_non_negative(self, "overshoot", "state_noise")
        if self.state_noise and self.obs != "state":
            raise ConfigError(f"state_noise perturbs what a state encoder reads, got "
                              f"state_noise={self.state_noise} with obs={self.obs!r}")
        if self.symlog and not self.decodes_state:
            raise ConfigError(f"symlog reads and reconstructs a state, got symlog=True with "
                              f"obs={self.obs!r} and recon={self.recon!r}")
        if self.state_hidden and self.obs != "state":
            raise ConfigError(f"state_hidden hides what a state encoder reads, got "
                              f"state_hidden={list(self.state_hidden)} with obs={self.obs!r}")
        if self.state_hidden and (len(set(self.state_hidden)) != len(self.state_hidden) or not
                                  all(0 <= i < self.state_dim for i in self.state_hidden)):
            raise ConfigError(f"state_hidden must hold distinct indices in [0, {self.state_dim}) "
                              f"(state_dim), got {list(self.state_hidden)}")
        if self.overshoot and self.obs != "state":
            raise ConfigError(f"overshoot is for state models (decoding images open-loop would "
                              f"dominate the update), got overshoot={self.overshoot} with "
                              f"obs={self.obs!r}")
        if self.obs == "state" or self.recon == "state":
            require_positive(self, "state_dim")

    @property
    def decodes_state(self) -> bool:
        return self.obs == "state" or self.recon == "state"


@dataclass(frozen=True)
class DreamerConfig:
    """A Dreamer agent: a world model (on state or images) plus actor-critic in imagination."""

    world_model: WorldModelConfig = field(default_factory=WorldModelConfig)
    """World model."""
    actor_critic: ActorCriticConfig = field(default_factory=ActorCriticConfig)
    """Behaviour learning."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Optimiser settings."""


@dataclass(frozen=True)
class TeacherConfig(DreamerConfig):
    """The state teacher: a Dreamer whose world model reads privileged state."""

    explore_noise: float = 0.0
    """Std of Gaussian noise added to sampled actions when acting with ``explore=True``
    (DreamerV2 explores by sampling its stochastic actor; this adds more on top)."""

    def __post_init__(self) -> None:
        if self.world_model.obs != "state":
            raise ConfigError(f"the teacher's world model reads state, got obs={self.world_model.obs!r}")
        if self.explore_noise < 0:
            raise ConfigError(f"explore_noise must be >= 0, got {self.explore_noise}")


@dataclass(frozen=True)
class ReadOutConfig:
    """A student that reads the teacher's state from images (the ``readout`` recipe): a CNN
    reads the components one frame shows, each velocity is a gain times the difference of
    successive read-outs or, where it is the rate of nothing one frame shows, read from a
    pair of frames of one scene, and the teacher's own state encoder, filter and actor take it
    from there (:mod:`twist_models.readout` pairs the components on D)."""

    state_dim: int = 1
    """Length of the teacher's state vector."""
    read: tuple[int, ...] = (0,)
    """State components the CNN reads from a single frame (what one image shows)."""
    angles: tuple[tuple[int, int], ...] = ()
    """(cos, sin) component pairs of ``read`` that lie on the unit circle: their angle is
    what a velocity differentiates."""
    velocities: tuple[tuple[int, ...], ...] = ()
    """One entry per derived component: (its index, a read index) for a linear difference, or
    (its index, cos index, sin index) for an angle difference."""
    gains: tuple[float, ...] = ()
    """Per entry of ``velocities``: the least-squares factor from the difference to the
    velocity on D (1 / the time between frames, up to the integrator's lag)."""
    encoder: MLPConfig = field(default_factory=MLPConfig)
    """The teacher's state encoder (copied with its weights and kept fixed)."""
    hidden: tuple[int, ...] = ()
    """State components the teacher never reads (its ``state_hidden``): neither read nor
    derived, handed on as 0, as the teacher's own encoder sees them."""
    symlog: bool = False
    """Whether the teacher's encoder reads the state through symlog (its world model's
    ``symlog``), which the copy embedding the reading must too."""
    moving: tuple[int, ...] = ()
    """Velocities that are the rate of nothing one frame shows (a tracked root's speed): read
    by a head on the CNN's features of the step's frame pair, the step before and the step
    in one scene (D's ``pair_image``; acting: the episode's previous frame)."""
    moving_pairing: tuple[float, ...] = ()
    """Per ``moving`` velocity, its best correlation with a read component's change on D
    (below ``ReadOutStage.min_pairing``; empty in runs recorded before it was kept)."""
    mirror: tuple[float, ...] = ()
    """Per component of ``read``, the sign it takes when the view is mirrored left to right
    (the task's ``TaskSpec.mirror``): given, each image is read as the mean of its own reading
    and its mirror image's, mirrored back; empty, as it is."""
    lean: float = 1.0
    """How much further from its centre each (cos, sin) angle is handed to the filter than it
    is read, near that centre: D's median angle, or 0 for an angle the mirror turns over (1:
    as read; the map is monotone and leaves the opposite angle where it is, so it needs
    0 < lean < 2; :meth:`StateReadOut.positions`)."""
    pooled: tuple[int, ...] = ()
    """Read components no episode of D changes (``panda-push``'s goal marker): each is handed
    on as the mean of its readings over the episode so far, so errors that differ between
    frames average out; empty, every frame read afresh (``ReadOutStage.pool``)."""

    def poolable(self) -> tuple[int, ...]:
        """The read components ``pooled`` may name: neither in an angle pair (pooled, it
        would leave the unit circle) nor the source of a velocity (which needs its change)."""
        excluded = {i for velocity in self.velocities for i in velocity[1:]} | {
            i for pair in self.angles for i in pair}
        return tuple(i for i in self.read if i not in excluded)

    def __post_init__(self) -> None:
        require_positive(self, "state_dim")
        if self.mirror and (len(self.mirror) != len(self.read)
                            or any(abs(v) != 1 for v in self.mirror)):
            raise ConfigError(f"mirror needs a sign (+1 or -1) per read component "
                              f"({len(self.read)}), got {list(self.mirror)}")
        if not 0 < self.lean < 2:
            raise ConfigError(f"lean must lie in (0, 2) for the reading's map to stay "
                              f"monotone, got {self.lean}")
        derived = [v[0] for v in self.velocities]
        every = [*self.read, *derived, *self.moving, *self.hidden]
        if sorted(every) != list(range(self.state_dim)):
            raise ConfigError(f"read {list(self.read)}, derived {derived}, moving "
                              f"{list(self.moving)} and hidden {list(self.hidden)} components "
                              f"must cover the state's {self.state_dim} components exactly once")
        for pair in self.angles:
            if len(pair) != 2 or not set(pair) <= set(self.read):
                raise ConfigError(f"an angle pair must be two read components, got {pair}")
        for velocity in self.velocities:
            sources = velocity[1:]
            if len(sources) not in (1, 2) or not set(sources) <= set(self.read) or (
                    len(sources) == 2 and tuple(sources) not in self.angles):
                raise ConfigError(f"velocity {velocity[0]} must come from one read component "
                                  f"or one angle pair, got sources {list(sources)}")
        if len(self.gains) != len(self.velocities):
            raise ConfigError(f"gains needs one factor per velocity ({len(self.velocities)}), "
                              f"got {len(self.gains)}")
        if not set(self.pooled) <= set(self.poolable()):
            raise ConfigError(f"pooled components must be read ones, neither in an angle pair "
                              f"nor the source of a velocity, got {list(self.pooled)}")


@dataclass(frozen=True)
class StudentConfig:
    """The vision student: a CNN encoder and an RSSM of the teacher's sizes. It has no decoder
    or heads: it learns only by matching the teacher's latents (Eq. 3 and 4)."""

    rssm: RSSMConfig = field(default_factory=RSSMConfig)
    """RSSM sizes; deter, stoch and classes must be the teacher's (its actor reads them)."""
    action_dim: int = 1
    """Length of the action vector."""
    cnn: CNNConfig = field(default_factory=CNNConfig)
    """Image encoder (its image_size is the dataset's)."""
    frames: int = 1
    """Images the posterior reads per step: the current one and the ``frames - 1`` before it,
    each encoded alone by the CNN (1: the paper's single image)."""
    state_dim: int = 0
    """Length of the privileged state a linear head reads from the posterior's image input,
    a training target of the ``dense`` recipe (0: no head, the paper's student; acting never
    uses it)."""
    readout: ReadOutConfig | None = None
    """Read the teacher's state from each image and let the teacher's state encoder embed it
    (the ``readout`` recipe; None: the CNN's embedding is the posterior's input, the paper)."""

    def __post_init__(self) -> None:
        require_positive(self, "action_dim", "frames")
        require_non_negative(self, "state_dim")
        if self.readout is not None and self.frames != 1:
            raise ConfigError(f"a read-out student reads one frame per step (its velocities "
                              f"are differences of successive read-outs), got frames={self.frames}")


@dataclass(frozen=True)
class AgentConfig:
    """A deployable image agent: the student's encoder and RSSM plus the teacher's actor."""

    student: StudentConfig = field(default_factory=StudentConfig)
    """The distilled student."""
    actor_critic: ActorCriticConfig = field(default_factory=ActorCriticConfig)
    """The teacher's behaviour config (its actor network and minimum std are used)."""


def _tiny_mlp() -> MLPConfig:
    return MLPConfig(layers=2, units=32)


#: Named size presets: ``paper`` is DreamerV2/TWIST; ``quick`` is a CPU-sized model for demos;
#: ``tiny`` is for tests.
PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "quick": {"rssm": RSSMConfig(deter=128, hidden=128, stoch=16, classes=16),
              "state_mlp": MLPConfig(layers=2, units=256), "head": MLPConfig(layers=2, units=256),
              "cnn": CNNConfig(depth=24)},
    "tiny": {"rssm": RSSMConfig(deter=32, hidden=32, stoch=4, classes=4),
             "state_mlp": _tiny_mlp(), "head": _tiny_mlp(), "cnn": CNNConfig(depth=4)},
}
_AC_PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "quick": {"actor": MLPConfig(layers=2, units=256), "critic": MLPConfig(layers=2, units=256)},
    # Tests and smoke runs: a short horizon keeps imagination, most of an update, cheap.
    "tiny": {"actor": _tiny_mlp(), "critic": _tiny_mlp(), "horizon": 5},
}


#: Named ways a teacher learns, applied over a size preset by :func:`teacher_preset`:
#: ``dreamerv2`` is DreamerV2's DMC settings (the configs' defaults); ``cpu`` the settings that
#: learned fastest on a 2-core CPU, each a change from DreamerV2's (a faster actor on fewer
#: imagination starts, a two-hot critic, DreamerV3's return normalisation, a faster world model
#: with open-loop overshooting; bfloat16 imagination where native), for action repeat 4.
LEARNING_PRESETS: dict[str, dict[str, Any]] = {
    "dreamerv2": {},
    "cpu": {"actor_critic.imag_starts": 256, "actor_critic.actor_lr": 1e-3,
            "actor_critic.critic_lr": 3e-4, "actor_critic.critic_head": "twohot",
            "actor_critic.return_norm": True, "actor_critic.slow_target_every": 50,
            "actor_critic.discount": 0.98, "actor_critic.precision": "auto",
            "world_model.model_lr": 1e-3, "world_model.overshoot": 15},
}


def teacher_preset(name: str, state_dim: int, action_dim: int,
                   learning: str = "dreamerv2") -> TeacherConfig:
    """The teacher config of size preset ``name`` for a task's state and action sizes, learning
    as :data:`LEARNING_PRESETS` ``learning`` says."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; valid presets are: {', '.join(PRESETS)}")
    if learning not in LEARNING_PRESETS:
        raise ConfigError(f"unknown learning preset {learning!r}; valid: "
                          f"{', '.join(LEARNING_PRESETS)}")
    world_model = WorldModelConfig(obs="state", state_dim=state_dim, action_dim=action_dim,
                                   **PRESETS[name])
    return replace_fields(TeacherConfig(world_model=world_model,
                                        actor_critic=ActorCriticConfig(**_AC_PRESETS[name])),
                          LEARNING_PRESETS[learning])


def image_dreamer_preset(name: str, state_dim: int, action_dim: int, image_size: int = 64,
                         recon: str = "obs") -> DreamerConfig:
    """A Dreamer of preset ``name`` sizes on images (the paper's Dreamer baselines), decoding
    the image (``recon="obs"``) or the privileged state (``recon="state"``: State Recon)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; valid presets are: {', '.join(PRESETS)}")
    sizes = dict(PRESETS[name])
    sizes["cnn"] = dataclasses.replace(sizes.get("cnn", CNNConfig()), image_size=image_size)
    world_model = WorldModelConfig(obs="image", state_dim=state_dim, action_dim=action_dim,
                                   recon=recon, **sizes)
    return DreamerConfig(world_model=world_model,
                         actor_critic=ActorCriticConfig(**_AC_PRESETS[name]))


def student_preset(name: str, teacher: TeacherConfig, image_size: int = 64,
                   frames: int = 1, norm: str = "none", state_head: bool = False,
                   readout: ReadOutConfig | None = None) -> StudentConfig:
    """The student of size preset ``name`` (its CNN normalised by ``norm``) for ``teacher``,
    whose RSSM it copies, reading ``frames`` images per step, with a read-out head of the
    teacher's state if ``state_head``, reading the state as ``readout`` pairs it if given."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; valid presets are: {', '.join(PRESETS)}")
    cnn = dataclasses.replace(PRESETS[name].get("cnn", CNNConfig()), image_size=image_size,
                              norm=norm)
    return StudentConfig(rssm=teacher.world_model.rssm, action_dim=teacher.world_model.action_dim,
                         cnn=cnn, frames=frames,
                         state_dim=teacher.world_model.state_dim if state_head else 0,
                         readout=readout)


def to_json(config: Any) -> dict[str, Any]:
    """A config as plain JSON types."""
    return json_safe(dataclasses.asdict(config))


def json_safe(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def json_leaves(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """A config's JSON (:func:`to_json`) as {dotted name: value} of its leaves, nested configs
    opened (``schedule.eval_every``), as ``--set`` names them."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            out.update(json_leaves(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def removed_fields(cls: type) -> Mapping[str, Any]:
    """The fields ``cls`` once had and no longer has, each with the value that meant "off":
    its ``REMOVED`` class attribute (a settings switch that no recipe used is removed, and a
    run recorded before keeps loading as long as it left the switch off)."""
    return getattr(cls, "REMOVED", {})


def moved_fields(cls: type) -> Mapping[str, str]:
    """The fields ``cls`` once had at its top level and now holds in a nested config, each
    with its dotted new name: its ``MOVED`` class attribute."""
    return getattr(cls, "MOVED", {})


def with_moved(cls: type, data: Mapping[str, Any]) -> dict[str, Any]:
    """A stored config of ``cls`` with the top-level fields that since moved into nested
    configs put where they are now (:func:`moved_fields`), so that a run recorded before
    loads, resumes and compares as it was."""
    moved = moved_fields(cls)
    out = {k: v for k, v in data.items() if k not in moved}
    for old, new in moved.items():
        if old in data:
            head, _, name = new.partition(".")
            out[head] = {**out.get(head, {}), name: data[old]}
    return out


def without_removed(cls: type, data: Mapping[str, Any]) -> dict[str, Any]:
    """A stored config of ``cls`` (:func:`to_json` output, nested configs too) without the
    removed fields it holds at their "off" value (:func:`removed_fields`), which change
    nothing; a removed field at any other value stays, for the caller to refuse."""
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    removed, hints, out = removed_fields(cls), typing.get_type_hints(cls), {}
    for name, value in data.items():
        if name not in names:
            if name not in removed or value != removed[name]:
                out[name] = value
            continue
        kind = nested_config_type(hints[name])
        out[name] = (without_removed(kind, value)
                     if kind is not None and isinstance(value, Mapping) else value)
    return out


def from_json(cls: type[T], data: Mapping[str, Any]) -> T:
    """Rebuild a (nested) config dataclass from :func:`to_json` output. Unknown keys are
    errors, except a removed field (:func:`removed_fields`) at its "off" value, which is
    dropped; one at any other value is refused, since the run it records used code that is
    gone."""
    data = without_removed(cls, with_moved(cls, data))
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    removed = removed_fields(cls)
    for name in sorted(set(data) - set(fields)):
        if name in removed:
            raise ConfigError(f"{cls.__name__}.{name} was removed (no recipe used it); this "
                              f"config sets it to {data[name]!r}, which only the removed "
                              f"code ran")
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"unknown fields {unknown} for {cls.__name__}")
    kwargs = {}
    hints = typing.get_type_hints(cls)
    for name, value in data.items():
        kind = nested_config_type(hints[name])
        if kind is not None and isinstance(value, Mapping):
            value = from_json(kind, value)
        elif isinstance(value, list):
            value = _as_tuples(value)
        kwargs[name] = value
    return cls(**kwargs)


def _as_tuples(value: Any) -> Any:
    """JSON lists back to the (nested) tuples a frozen config holds."""
    return tuple(_as_tuples(v) for v in value) if isinstance(value, list) else value


def nested_config_type(hint: Any) -> type | None:
    """The config dataclass a field annotation holds (``X`` or ``X | None``), else None."""
    if dataclasses.is_dataclass(hint):
        return hint
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        kinds = [k for k in typing.get_args(hint) if dataclasses.is_dataclass(k)]
        return kinds[0] if len(kinds) == 1 else None
    return None


def field_types(config_type: type) -> dict[str, Any]:
    """Every settable field of the config dataclass ``config_type`` and its annotation, a
    nested config's fields under dotted names (``optim.grad_clip``) beside the nested config
    itself."""
    found: dict[str, Any] = {}
    for name, hint in typing.get_type_hints(config_type).items():
        if name not in {f.name for f in dataclasses.fields(config_type)}:
            continue
        found[name] = hint
        nested = nested_config_type(hint)
        if nested is not None:
            found.update({f"{name}.{k}": v for k, v in field_types(nested).items()})
    return found


def replace_fields(config: T, settings: Mapping[str, Any]) -> T:
    """``config`` with the fields in ``settings`` replaced; a dotted key (``optim.grad_clip``)
    replaces a field of a nested config and keeps its other fields, and a field's name from
    before it moved into a nested config (:func:`moved_fields`) reaches it there, as a stored
    run's does. An unknown field is a :class:`ConfigError` naming it."""
    top: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    names = {f.name for f in dataclasses.fields(config)}  # type: ignore[arg-type]
    moved = moved_fields(type(config))
    for key, value in settings.items():
        key = moved.get(key, key)
        head, dot, rest = key.partition(".")
        if head not in names:
            raise ConfigError(f"{type(config).__name__} has no field {key!r}")
        if dot:
            nested.setdefault(head, {})[rest] = value
        else:
            top[head] = value
    for head, inner in nested.items():
        base = top.get(head, getattr(config, head))
        if not dataclasses.is_dataclass(base):
            raise ConfigError(f"{type(config).__name__}.{head} is not a nested config, so "
                              f"{head}.{next(iter(inner))} cannot be set")
        top[head] = replace_fields(base, inner)
    return dataclasses.replace(config, **top)  # type: ignore[type-var]
