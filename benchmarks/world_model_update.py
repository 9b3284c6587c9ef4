"""World-model update times on this machine, each beside a naive baseline run in the
same process.

* ``teacher``: one full teacher update (state world model + actor-critic in imagination), and
  the world-model part alone; state of cheetah-run's size (17), 6 actions.
* ``student``: one student forward/backward + Adam step: 64x64 images -> CNN encoder -> RSSM
  ``observe`` -> a matching loss on (h, posterior, prior) against fixed targets (the cost of
  Eq. 3; no decoder). Images are uint8 as the sampler yields them.
* Baselines: a naive eager skeleton of the same shapes written the obvious way (NCHW
  convolutions, every head inside the time loop, ``torch.multinomial`` sampling), the
  reference the issue's figures (0.34 s world model, 1.9 s student) were taken with.

B=16, L=50, sizes of ``--preset`` (default paper = DreamerV2 DMC), random data (timings do not
depend on values). Each figure is the median over ``--repeats`` updates after one warm-up.
Prints one JSON line per part.

``--compile`` adds, on copies of the same weights: the teacher's world-model update with its
loss (forward, and through it the backward) in ``torch.compile``; the teacher's whole update
as the collector compiles it (``Dreamer.compile_update``); the student update with its loss
compiled whole, and in pieces (``student_pieces_s``: the filter run ``FILTER_CHUNK`` steps at
a time through ``RSSM.compile_filter``, the CNN eager, as ``twist-distil --set compile=true``
runs on a CPU: ``twist_models.distillation.compiled_objective``). ``--precision bfloat16``
runs the student's CNN under bfloat16 autocast in every variant, eager included, as the
``dense`` and ``readout`` recipes do where the device computes bfloat16 natively. Each
variant's first two calls are reported apart (``<name>_compile_s``) and ``<name>_speedup``
is the eager median over the compiled one, both from the same run; a compiler failure is
reported as ``<name>_error``. ``--compile-mode reduce-overhead`` adds
CUDA graphs on a GPU.

    python benchmarks/world_model_update.py [--part teacher|student|all] [--preset paper]
        [--repeats 5] [--device cpu|cuda] [--imag-starts N] [--compile]
        [--compile-mode default|reduce-overhead|max-autotune-no-cudagraphs]
        [--precision float32|bfloat16]
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import statistics
import time
import traceback
from collections.abc import Callable

import torch
from torch import nn
from torch.nn import functional as F

from twist_models.config import PRESETS, RSSMConfig, WorldModelConfig, teacher_preset
from twist_models.device import precision_autocast
from twist_models.losses import categorical_kl
from twist_models.networks import MLP
from twist_models.rssm import FILTER_CHUNK
from twist_models.teacher import Teacher
from twist_models.world_model import WorldModel

TARGETS_S = {("teacher", "cpu"): 0.25, ("student", "cpu"): 1.0, ("teacher", "cuda"): 0.030,
             ("student", "cuda"): 1 / 30}
B, L, STATE, ACTIONS = 16, 50, 17, 6


def median_time(update: Callable[[], None], repeats: int, device: torch.device) -> list[float]:
    update()  # warm-up (allocations, cuDNN autotuning)
    samples = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        update()
        if device.type == "cuda":
            torch.cuda.synchronize()
        samples.append(time.perf_counter() - start)
    return samples


def sequence_batch(device: torch.device, image: bool) -> dict[str, torch.Tensor]:
    is_first = torch.zeros(B, L, dtype=torch.bool, device=device)
    is_first[:, 0] = True
    batch = {"action": torch.rand(B, L, ACTIONS, device=device) * 2 - 1,
             "reward": torch.rand(B, L, device=device), "is_first": is_first,
             "state": torch.randn(B, L, STATE, device=device)}
    if image:
        batch["image"] = torch.randint(0, 256, (B, L, 64, 64, 3), dtype=torch.uint8,
                                       device=device)
    return batch


# -- the naive baseline ---------------------------------------------------------------------
class NaiveSkeleton(nn.Module):
    """The same shapes written the obvious way: heads and sampling inside the time loop."""

    def __init__(self, rssm: RSSMConfig, embed: nn.Module, embed_dim: int) -> None:
        super().__init__()
        latent = rssm.stoch * rssm.classes
        self.rssm = rssm
        self.embed = embed
        self.img_in = nn.Linear(latent + ACTIONS, rssm.hidden)
        self.gru = nn.GRUCell(rssm.hidden, rssm.deter)
        self.prior = nn.Sequential(nn.Linear(rssm.deter, rssm.hidden), nn.ELU(),
                                   nn.Linear(rssm.hidden, latent))
        self.post = nn.Sequential(nn.Linear(rssm.deter + embed_dim, rssm.hidden), nn.ELU(),
                                  nn.Linear(rssm.hidden, latent))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> dict[str, torch.Tensor]:
        embed = self.embed(obs)
        r = self.rssm
        deter = obs.new_zeros(B, r.deter, dtype=torch.float32)
        stoch = obs.new_zeros(B, r.stoch * r.classes, dtype=torch.float32)
        out: dict[str, list[torch.Tensor]] = {"deter": [], "post": [], "prior": []}
        for t in range(L):
            deter = self.gru(F.elu(self.img_in(torch.cat([stoch, action[:, t]], -1))), deter)
            prior = self.prior(deter).unflatten(-1, (r.stoch, r.classes))
            post = self.post(torch.cat([deter, embed[:, t]], -1)).unflatten(-1, (r.stoch,
                                                                                 r.classes))
            probs = post.softmax(-1)
            index = torch.multinomial(probs.reshape(-1, r.classes), 1).reshape(B, r.stoch)
            sample = F.one_hot(index, r.classes).float()
            stoch = (sample + probs - probs.detach()).flatten(-2)
            for key, value in (("deter", deter), ("post", post), ("prior", prior)):
                out[key].append(value)
        return {k: torch.stack(v, 1) for k, v in out.items()}


def naive_cnn(depth: int) -> nn.Module:
    layers: list[nn.Module] = []
    channels = 3
    for i in range(4):
        layers += [nn.Conv2d(channels, depth * 2**i, 4, stride=2), nn.ELU()]
        channels = depth * 2**i
    # [B*L, 3, 64, 64] -> [B, L, E]
    return nn.Sequential(*layers, nn.Flatten(1), nn.Unflatten(0, (B, L)))


# -- parts ----------------------------------------------------------------------------------
def matching_loss(deter: torch.Tensor, post: torch.Tensor, prior: torch.Tensor,
                  target: dict[str, torch.Tensor]) -> torch.Tensor:
    return (F.mse_loss(deter, target["deter"]) + categorical_kl(target["post"], post).mean()
            + categorical_kl(target["prior"], prior).mean())


def compiled_variant(update: Callable[[], None], repeats: int, device: torch.device
                     ) -> tuple[list[float], float]:
    """Samples of a compiled update after its first call, and that first call's seconds.
    CUDA graphs (mode reduce-overhead) record on the second and third calls, so two calls
    count as compilation there."""
    start = time.perf_counter()
    update()
    update()
    if device.type == "cuda":
        torch.cuda.synchronize()
    first = time.perf_counter() - start
    return median_time(update, repeats, device), first


def try_compiled(samples: dict[str, list[float]], extra: dict[str, object], name: str,
                 update: Callable[[], None], repeats: int, device: torch.device,
                 eager: str) -> None:
    """Time ``update`` as ``samples[name]``; a compiler failure is reported, not raised."""
    try:
        samples[name], first = compiled_variant(update, repeats, device)
    except Exception as error:  # the JSON line reports any compiler failure
        extra[f"{name}_error"] = f"{type(error).__name__}: {str(error)[:300]}"
        traceback.print_exc()
        return
    extra[f"{name}_compile_s"] = round(first, 1)
    extra[f"{name}_speedup"] = round(statistics.median(samples[eager])
                                     / statistics.median(samples[name]), 2)


def bench_teacher(preset: str, repeats: int, device: torch.device,
                  imag_starts: int | None = None, compile_too: bool = False,
                  compile_mode: str = "default", whole_only: bool = False) -> dict[str, object]:
    torch.manual_seed(0)
    config = teacher_preset(preset, STATE, ACTIONS)
    if imag_starts is not None:
        config = dataclasses.replace(config, actor_critic=dataclasses.replace(
            config.actor_critic, imag_starts=imag_starts))
    teacher = Teacher(config).to(device)
    batch = sequence_batch(device, image=False)

    def world_model_only() -> None:
        loss, _, _ = teacher.world_model.loss(batch)
        teacher.model_opt.zero_grad(set_to_none=True)
        loss.backward()
        teacher.model_opt.step()

    wm = config.world_model
    naive = NaiveSkeleton(wm.rssm, nn.Sequential(
        nn.Linear(STATE, 512), nn.ELU(), nn.Linear(512, 512), nn.ELU(), nn.Linear(512, 512),
        nn.ELU()), 512).to(device)
    decoder = MLP(wm.rssm.feature_dim, STATE, wm.state_mlp).to(device)
    reward_head = MLP(wm.rssm.feature_dim, 1, wm.head).to(device)
    naive_opt = torch.optim.Adam([*naive.parameters(), *decoder.parameters(),
                                  *reward_head.parameters()], 3e-4)

    def naive_world_model() -> None:
        out = naive(batch["state"], batch["action"])
        feature = torch.cat([out["deter"], out["post"].flatten(-2)], -1)
        loss = (categorical_kl(out["post"], out["prior"]).mean()
                + F.mse_loss(decoder(feature), batch["state"])
                + F.mse_loss(reward_head(feature).squeeze(-1), batch["reward"]))
        naive_opt.zero_grad()
        loss.backward()
        naive_opt.step()

    samples = {"naive_world_model_s": median_time(naive_world_model, repeats, device),
               "world_model_s": median_time(world_model_only, repeats, device),
               "teacher_update_s": median_time(lambda: teacher.train_step(batch), repeats,
                                               device)}
    extra: dict[str, object] = {}
    if compile_too and not whole_only:
        twin = copy.deepcopy(teacher)
        twin_opt = torch.optim.AdamW(twin.world_model.parameters(), wm.model_lr, eps=1e-5)
        compiled_loss = torch.compile(twin.world_model.loss, mode=compile_mode)

        def world_model_compiled() -> None:
            torch.compiler.cudagraph_mark_step_begin()
            loss, _, _ = compiled_loss(batch)
            twin_opt.zero_grad(set_to_none=True)
            loss.backward()
            twin_opt.step()

        try_compiled(samples, extra, "world_model_compiled_s", world_model_compiled, repeats,
                     device, "world_model_s")
    if compile_too:
        # The whole update as the collector compiles it (Dreamer.compile_update).
        whole = copy.deepcopy(teacher)
        whole.compile_update(compile_mode)
        try_compiled(samples, extra, "teacher_compiled_s", lambda: whole.train_step(batch),
                     repeats, device, "teacher_update_s")
    medians = {k: statistics.median(v) for k, v in samples.items()}
    return {"samples": samples, "medians": medians, "figure": "teacher_update_s", **extra,
            "imag_starts": config.actor_critic.imag_starts or B * L,
            "actor_critic_share": round(1 - medians["world_model_s"]
                                        / medians["teacher_update_s"], 2),
            "world_model_speedup_vs_naive": round(medians["naive_world_model_s"]
                                                  / medians["world_model_s"], 2)}


def bench_student(preset: str, repeats: int, device: torch.device,
                  imag_starts: int | None = None, compile_too: bool = False,
                  compile_mode: str = "default", precision: str = "float32"
                  ) -> dict[str, object]:
    torch.manual_seed(0)
    base = teacher_preset(preset, STATE, ACTIONS).world_model
    config = WorldModelConfig(obs="image", state_dim=STATE, action_dim=ACTIONS, rssm=base.rssm,
                              cnn=base.cnn, head=base.head)
    student = WorldModel(config).to(device)
    batch = sequence_batch(device, image=True)
    r = config.rssm
    target = {"deter": torch.randn(B, L, r.deter, device=device),
              "post": torch.randn(B, L, r.stoch, r.classes, device=device),
              "prior": torch.randn(B, L, r.stoch, r.classes, device=device)}

    def student_loss(model: WorldModel) -> torch.Tensor:
        with precision_autocast(precision, device):  # the CNN only, as the recipes run it
            features = model.embed(batch["image"]).float()
        post, prior = model.rssm.observe(features, batch["action"], batch["is_first"])
        return matching_loss(post["deter"], post["logits"], prior["logits"], target)

    def updater(model: WorldModel, loss_of: Callable[[WorldModel], torch.Tensor]
                ) -> Callable[[], None]:
        """One update of ``model``'s encoder and RSSM with an AdamW of its own."""
        optimiser = torch.optim.AdamW([*model.encoder.parameters(), *model.rssm.parameters()],
                                      config.model_lr, eps=1e-5)

        def update() -> None:
            torch.compiler.cudagraph_mark_step_begin()  # a no-op without CUDA graphs
            loss = loss_of(model)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()

        return update

    student_update = updater(student, student_loss)

    naive = NaiveSkeleton(r, naive_cnn(config.cnn.depth), student.perception.encoder.out_dim).to(device)
    naive_opt = torch.optim.Adam(naive.parameters(), 3e-4)

    def naive_update() -> None:
        images = batch["image"].flatten(0, 1).permute(0, 3, 1, 2).float() / 255 - 0.5
        out = naive(images, batch["action"])
        loss = matching_loss(out["deter"], out["post"], out["prior"], target)
        naive_opt.zero_grad()
        loss.backward()
        naive_opt.step()

    samples = {"naive_student_s": median_time(naive_update, repeats, device),
               "student_update_s": median_time(student_update, repeats, device)}
    extra: dict[str, object] = {}
    if compile_too:
        try_compiled(samples, extra, "student_compiled_s",
                     updater(copy.deepcopy(student), torch.compile(student_loss, mode=compile_mode)),
                     repeats, device, "student_update_s")
        if compile_mode != "reduce-overhead":  # CUDA graphs want the whole graph
            pieces = copy.deepcopy(student)
            pieces.rssm.compile_filter(FILTER_CHUNK, compile_mode)
            student_pieces = updater(pieces, student_loss)
            try_compiled(samples, extra, "student_pieces_s", student_pieces, repeats, device,
                         "student_update_s")
    medians = {k: statistics.median(v) for k, v in samples.items()}
    return {"samples": samples, "medians": medians, "figure": "student_update_s", **extra,
            "speedup_vs_naive": round(medians["naive_student_s"]
                                      / medians["student_update_s"], 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", default="all", choices=["teacher", "student", "all"])
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--imag-starts", type=int, default=None,
                        help="override the preset's imagination starts (teacher part)")
    parser.add_argument("--compile", action="store_true",
                        help="also time the updates with their loss in torch.compile")
    parser.add_argument("--compile-mode", default="default",
                        choices=["default", "reduce-overhead", "max-autotune-no-cudagraphs"],
                        help="torch.compile's mode (reduce-overhead: CUDA graphs)")
    parser.add_argument("--whole-only", action="store_true",
                        help="of the teacher's compiled variants, only the whole update")
    parser.add_argument("--precision", default="float32", choices=["float32", "bfloat16"],
                        help="the student's CNN under bfloat16 autocast (every variant)")
    args = parser.parse_args()
    device = torch.device(args.device)
    parts = ["teacher", "student"] if args.part == "all" else [args.part]
    for part in parts:
        options = ({"whole_only": args.whole_only} if part == "teacher"
                   else {"precision": args.precision})
        result = {"teacher": bench_teacher, "student": bench_student}[part](
            args.preset, args.repeats, device, args.imag_starts, args.compile, args.compile_mode,
            **options)
        medians = result.pop("medians")
        samples = result.pop("samples")
        figure = result.pop("figure")
        # The target is for the update as a run would make it: compiled where --compile
        # timed a compiled variant, else eager.
        if f"{part}_compiled_s" in medians:
            figure = f"{part}_compiled_s"
        target = TARGETS_S.get((part, device.type))
        print(json.dumps({
            "benchmark": f"{part}_update", "preset": args.preset, "batch": B, "length": L,
            "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
            "threads": torch.get_num_threads(), "cpus": os.cpu_count(),
            **{k: round(v, 4) for k, v in medians.items()}, **result,
            "compile_mode": args.compile_mode if args.compile else None,
            "precision": args.precision if part == "student" else None,
            "judged": figure, "target_s": target, "meets_target": None if target is None
            else medians[figure] <= target,
            "samples": {k: [round(x, 4) for x in v] for k, v in samples.items()},
        }), flush=True)


if __name__ == "__main__":
    main()
