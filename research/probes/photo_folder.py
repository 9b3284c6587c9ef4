"""Write a folder of held-out photographs for ``twist-eval --backgrounds DIR``, taken from
what installed packages ship, so nothing is downloaded.

One photograph (matplotlib's ``grace_hopper.jpg``) is a thin test of "a user's photograph
behind the scene": an agent can lose or pass on that one image by chance. scikit-image ships
several more in its wheel (``skimage/data``). This script writes the everyday photographs
among them, people, an animal, objects, a street scene and a grey one, as RGB PNGs beside
matplotlib's, skipping the textures, microscopy and drawings. None of them may be used for
training: they stand for the real scenes a student never saw.

Without scikit-image (``pip install scikit-image``; not a dependency of the package) only
matplotlib's photograph is written, and the script says so.

``python research/probes/photo_folder.py OUT``
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import cv2
import numpy as np

#: scikit-image's bundled photographs of everyday scenes (files in its wheel's ``data``
#: folder, read directly: its loader functions may try to fetch what a wheel lacks).
SKIMAGE_PHOTOS = ("astronaut.png", "chelsea.png", "coffee.png", "motorcycle_left.png",
                  "rocket.jpg", "camera.png", "hubble_deep_field.jpg")


def shipped_photographs() -> dict[str, np.ndarray]:
    """Name -> RGB uint8 image of every photograph found in the installed packages."""
    import matplotlib.cbook

    files = [Path(matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False))]
    spec = importlib.util.find_spec("skimage")
    if spec is not None and spec.origin is not None:
        folder = Path(spec.origin).parent / "data"
        files += [folder / name for name in SKIMAGE_PHOTOS if (folder / name).is_file()]
    # IMREAD_COLOR gives three channels for grey and RGBA files alike.
    return {path.stem: cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            for path in files}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    photos = shipped_photographs()
    for name, image in photos.items():
        cv2.imwrite(str(args.out / f"{name}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    print(f"wrote {len(photos)} photographs to {args.out}: {', '.join(photos)}")
    if len(photos) == 1:
        print("scikit-image is not installed: only matplotlib's photograph was written")


if __name__ == "__main__":
    main()
