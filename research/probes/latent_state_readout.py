"""What state does the student's latent hold? Read-outs along D's windows

Both models filter the same windows of D (the teacher on states, the student on images, the
actions executed; open loop), and from each model's features (h and z) this fits, on
training episodes, and scores on held-out episodes (every ``--holdout-every``-th, as
``twist-distil``):

* a ridge regression to each privileged state component: R² and RMSE in the state's units,
  to set beside ``oracle_noise_tolerance.py``'s tolerances;
* an MLP to the teacher's action (its actor's mode on its own latent): R², i.e. whether the
  student's latent holds what the actor needs in *any* decodable form, not only the
  teacher's;
* the teacher's actor itself on the student's features: R² of its action.

The teacher's own features are the baseline measured in the same run. The first
``--burn-in`` steps of each window are skipped while both filters settle.

Prints one JSON line. ``python research/probes/latent_state_readout.py DATASET STUDENT TEACHER
[--batches 30]`` (STUDENT: a ``student.pt`` of twist-distil; TEACHER: its ``teacher.pt``).
"""

from __future__ import annotations

import argparse
import json

import torch

from twist_data.sampler import SamplerConfig, WindowSampler
from twist_models.teacher import load_teacher
from twist_pipeline.distil import load_student


def r_squared(prediction: torch.Tensor, target: torch.Tensor) -> list[float]:
    """Per column: 1 - MSE / variance, for [N, D] tensors."""
    return (1 - ((prediction - target) ** 2).mean(0) / target.var(0)).tolist()


def rounded(values: list[float]) -> list[float]:
    return [round(v, 3) for v in values]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("student")
    parser.add_argument("teacher")
    parser.add_argument("--batches", type=int, default=30, help="training batches of 16x50")
    parser.add_argument("--burn-in", type=int, default=5)
    parser.add_argument("--holdout-every", type=int, default=10)
    parser.add_argument("--ridge", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    student = load_student(args.student)[0].eval()
    teacher = load_teacher(args.teacher)[0].eval()
    wm, actor = teacher.world_model, teacher.actor_critic.actor

    def features(split: str, batches: int, seed: int) -> dict[str, torch.Tensor]:
        sampler = WindowSampler(args.dataset, SamplerConfig(
            length=50, batch_size=16, seed=seed, holdout_every=args.holdout_every, split=split,
            keys=("image", "state", "action", "is_first")))
        out: dict[str, list[torch.Tensor]] = {"teacher": [], "student": [], "action": [],
                                              "state": []}
        for _ in range(batches):
            b = {k: torch.as_tensor(v) for k, v in sampler.batch().items()}
            with torch.no_grad():
                t_post, _ = wm.rssm.observe(wm.embed(b["state"]), b["action"], b["is_first"])
                s_post, _ = student.observe(b["image"], b["action"], b["is_first"])
                t_feature = wm.rssm.feature(t_post)
                rows = {"teacher": t_feature, "student": student.rssm.feature(s_post),
                        "action": actor(t_feature).mode, "state": b["state"]}
            for key, value in rows.items():
                out[key].append(value[:, args.burn_in:].flatten(0, 1))
        return {k: torch.cat(v) for k, v in out.items()}

    train = features("train", args.batches, args.seed + 1)
    test = features("heldout", max(args.batches // 4, 4), args.seed + 2)
    result: dict[str, object] = {"dataset": args.dataset, "student": args.student,
                                 "train_steps": len(train["state"]),
                                 "heldout_steps": len(test["state"]),
                                 "state_std": rounded(test["state"].std(0).tolist())}
    with torch.no_grad():
        result["teacher_actor_on_student_r2"] = rounded(
            r_squared(actor(test["student"]).mode, test["action"]))
    for name in ("teacher", "student"):
        x, x_test = train[name], test[name]
        mean, std = x.mean(0), x.std(0) + 1e-6
        a, a_test = (torch.cat([(v - mean) / std, torch.ones(len(v), 1)], 1)
                     for v in (x, x_test))
        weights = torch.linalg.solve(a.T @ a + args.ridge * torch.eye(a.shape[1]),
                                     a.T @ train["state"])
        prediction = a_test @ weights
        result[f"{name}_state_r2"] = rounded(r_squared(prediction, test["state"]))
        result[f"{name}_state_rmse"] = rounded(
            ((prediction - test["state"]) ** 2).mean(0).sqrt().tolist())
        net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 256), torch.nn.ELU(),
                                  torch.nn.Linear(256, 256), torch.nn.ELU(),
                                  torch.nn.Linear(256, train["action"].shape[1]))
        optimiser = torch.optim.Adam(net.parameters(), 1e-3)
        for _ in range(3000):
            pick = torch.randint(0, len(x), (512,))
            loss = ((net(x[pick]) - train["action"][pick]) ** 2).mean()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
        with torch.no_grad():
            result[f"{name}_mlp_action_r2"] = rounded(r_squared(net(x_test), test["action"]))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
