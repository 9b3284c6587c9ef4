"""Wheels for installing twist on a machine that cannot reach a package index but has its own
CUDA PyTorch (a GPU node's image): the packages of scripts/offline-requirements.txt, built for
that machine's Python, in one folder to copy there with the repository.

    python scripts/offline_bundle.py DIR [--python 3.12] [--requirements FILE]
    # on the GPU machine, from the repository's root:
    . scripts/offline_install.sh DIR [TARGET]

dm-control's wheel (56 MB) is slimmed to ~7 MB: it drops ``dm_control/locomotion`` and the
dog's meshes, which no twist task loads (``twist-data tasks``); mujoco's drops
``mujoco/experimental`` (its Studio app, ~40 MB unpacked), which nothing imports. So the bundle
and the repository fit where a transfer is limited.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import zipfile
from pathlib import Path

PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64",
             "manylinux_2_17_x86_64", "manylinux2014_x86_64", "manylinux1_x86_64")
#: Folders of a wheel that no twist task reads, by the wheel's distribution name.
UNUSED = {"dm_control": ("dm_control/locomotion/", "dm_control/suite/dog_assets/"),
          "mujoco": ("mujoco/experimental/",)}


def slim_wheel(wheel: Path, unused: tuple[str, ...]) -> int:
    """Rewrites ``wheel`` without the members under the ``unused`` folders (and their RECORD
    lines); returns how many members it dropped."""
    slim = wheel.with_suffix(".slim")
    dropped = 0
    with zipfile.ZipFile(wheel) as source, \
            zipfile.ZipFile(slim, "w", compression=zipfile.ZIP_DEFLATED) as target:
        for member in source.infolist():
            if member.filename.startswith(unused):
                dropped += 1
                continue
            data = source.read(member)
            if member.filename.endswith(".dist-info/RECORD"):
                lines = data.decode().splitlines(keepends=True)
                data = "".join(line for line in lines if not line.startswith(unused)).encode()
            target.writestr(member, data)
    slim.replace(wheel)
    return dropped


def download(requirements: Path, folder: Path, python: str) -> None:
    """The pinned wheels, without their dependencies (the list names each one the target's
    image lacks; pip cannot resolve against a machine it does not see)."""
    platforms = [arg for platform in PLATFORMS for arg in ("--platform", platform)]
    subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
                    "--python-version", python, "--implementation", "cp", *platforms,
                    "-d", str(folder), "-r", str(requirements)], check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--python", default="3.12", help="the GPU machine's Python version")
    parser.add_argument("--requirements", type=Path,
                        default=Path(__file__).with_name("offline-requirements.txt"))
    args = parser.parse_args()
    args.folder.mkdir(parents=True, exist_ok=True)
    download(args.requirements, args.folder, args.python)
    for name, unused in UNUSED.items():
        for wheel in args.folder.glob(f"{name}-*.whl"):
            print(f"{wheel.name}: dropped {slim_wheel(wheel, unused)} unused files")
    size = sum(path.stat().st_size for path in args.folder.glob("*.whl"))
    print(f"{args.folder}: {len(list(args.folder.glob('*.whl')))} wheels, {size / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
