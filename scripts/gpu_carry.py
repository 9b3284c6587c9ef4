"""The carry folder of a short GPU slot: what scripts/gpu_slot.sh needs beside the repository
to distil from a D that was collected elsewhere.

    python scripts/gpu_carry.py DATASET CARRY [--teacher T] [--wheels DIR] [--gl DIR]
                                [--limit-mib 60]

CARRY gets ``dataset/`` (DATASET stripped of its images: ``twist-data strip``), ``teacher.pt``
(the teacher's weights alone: DATASET's final teacher, or T) and, with ``--wheels``, the
``*.whl`` of DIR (``scripts/offline_bundle.py``: the packages a GPU image without a package
index lacks) and, with ``--gl``, the ``*.deb`` of DIR: the EGL/GL loader packages (libglvnd)
that a CUDA image may lack, without which MuJoCo cannot open an EGL context there
(``apt-get download libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2``; the slot unpacks
them). A slot uploads the repository and the carry together under a size limit (64 MiB
where this project's GPU is lent), so the command fails, and removes CARRY, when the files
the repository would send (tracked, and untracked but not ignored) plus CARRY exceed
``--limit-mib``.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


class CarryError(Exception):
    """The carry cannot be built, or is over the limit."""


def tree_bytes(root: Path = ROOT) -> int:
    """Bytes of the files a copy of the repository's working tree sends: tracked files and
    untracked ones that git does not ignore."""
    listed = subprocess.run(["git", "-C", str(root), "ls-files", "-z", "--cached", "--others",
                             "--exclude-standard"], check=True, capture_output=True).stdout
    paths = {root / name for name in listed.decode().split("\0") if name}
    return sum(path.stat().st_size for path in paths if path.is_file())


def folder_bytes(folder: Path) -> int:
    return sum(path.stat().st_size for path in folder.rglob("*") if path.is_file())


def build_carry(dataset: Path, carry: Path, teacher: Path | None = None,
                wheels: Path | None = None, limit_mib: float = 60.0,
                gl: Path | None = None) -> dict[str, int]:
    """Build ``carry`` (see the module's text); returns the bytes of each part and the
    total with the repository's tree. Nothing is left at ``carry`` when it fails."""
    from twist_data.reader import open_dataset
    from twist_data.strip import strip_dataset
    from twist_models.checkpoint import read_checkpoint, weights_only
    from twist_models.teacher import find_teacher

    task = open_dataset(dataset).spec.task  # a path that is not a dataset is named first
    if carry.exists():
        raise CarryError(f"carry folder {str(carry)!r} exists; remove it or name another")
    if wheels is not None and not sorted(wheels.glob("*.whl")):
        raise CarryError(f"{str(wheels)!r} holds no wheel (*.whl); make them with "
                         "scripts/offline_bundle.py")
    if gl is not None and not sorted(gl.glob("*.deb")):
        raise CarryError(f"{str(gl)!r} holds no package (*.deb); download the GL loaders "
                         "with apt-get download")
    source_teacher = teacher if teacher is not None else find_teacher(dataset)
    taught = read_checkpoint(source_teacher, kind="teacher").extra.get("collect", {}).get("task")
    if taught not in (None, task):
        raise CarryError(f"teacher {str(source_teacher)!r} learned {taught!r}, but the dataset "
                         f"is of {task!r}")
    try:
        strip_dataset(dataset, carry / "dataset")
        weights_only(source_teacher, carry / "teacher.pt")
        for source, name, pattern in ((wheels, "wheels", "*.whl"), (gl, "gl", "*.deb")):
            if source is not None:
                (carry / name).mkdir()
                for path in sorted(source.glob(pattern)):
                    shutil.copy2(path, carry / name / path.name)
        sizes = {"dataset": folder_bytes(carry / "dataset"),
                 "teacher": (carry / "teacher.pt").stat().st_size,
                 "wheels": folder_bytes(carry / "wheels") if wheels is not None else 0,
                 "gl": folder_bytes(carry / "gl") if gl is not None else 0,
                 "tree": tree_bytes()}
        # A carry inside the repository is ignored by git (or it would be sent twice).
        sizes["total"] = sizes["tree"] + sum(sizes[k] for k in ("dataset", "teacher", "wheels", "gl"))
        if sizes["total"] > limit_mib * 2**20:
            raise CarryError(
                "the repository's tree and the carry come to "
                f"{sizes['total'] / 2**20:.1f} MiB (tree {sizes['tree'] / 2**20:.1f}, dataset "
                f"{sizes['dataset'] / 2**20:.1f}, teacher {sizes['teacher'] / 2**20:.1f}, "
                f"wheels {sizes['wheels'] / 2**20:.1f}, GL {sizes['gl'] / 2**20:.1f}), "
                f"over the limit of {limit_mib:g} MiB")
    except BaseException:
        shutil.rmtree(carry, ignore_errors=True)
        raise
    return sizes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("carry", type=Path)
    parser.add_argument("--teacher", type=Path, help="teacher checkpoint [DATASET's final]")
    parser.add_argument("--wheels", type=Path, help="folder of scripts/offline_bundle.py")
    parser.add_argument("--gl", type=Path, help="folder of the GL loaders' *.deb packages")
    parser.add_argument("--limit-mib", type=float, default=60.0,
                        help="the most the tree and the carry may take together")
    args = parser.parse_args()
    from twist_data.errors import TwistError

    try:
        sizes = build_carry(args.dataset, args.carry, args.teacher, args.wheels, args.limit_mib,
                            args.gl)
    except (CarryError, TwistError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    print(" ".join(f"{k}={v / 2**20:.2f}MiB" for k, v in sizes.items()))


if __name__ == "__main__":
    main()
