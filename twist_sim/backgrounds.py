"""Background textures for domain randomisation: two disjoint procedural banks and user images.

The paper uses Distracting-Control video backgrounds (train vs validation videos). The machine
this toolkit targets has no internet, so the default banks are procedural and regenerated
bit-exactly from a seed: ``train`` draws from three texture families (fractal clouds, wave
stripes, rotated checkers), ``wide`` from those and two more (thin line segments, soft
ellipses), ``heldout`` from three *other* families (Voronoi cells, radial rings, Mondrian
rectangles). A held-out texture therefore never occurs in training, and the shift is one of
texture statistics, not only of seeds. ``leaves`` adds dead leaves, which have the
scale and occlusion statistics of photographs. ``--backgrounds DIR`` swaps in any
folder of photos, or video files whose frames are used.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import shutil
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from twist_data.errors import ConfigError
from twist_sim.errors import BackgroundError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp", ".tif", ".tiff")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".gif")

Generator = Callable[[np.random.Generator, int], np.ndarray]


def _palette(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform(0, 255, (n, 3)).astype(np.float32)


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    return yy, xx


def _to_image(value: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """Map values in [0, 1] through a piecewise-linear palette of colours -> uint8 RGB."""
    stops = np.linspace(0.0, 1.0, len(colours))
    channels = [np.interp(value, stops, colours[:, c]) for c in range(3)]
    return np.clip(np.stack(channels, -1), 0, 255).astype(np.uint8)


def clouds(rng: np.random.Generator, size: int) -> np.ndarray:
    """Fractal value noise: octaves of bicubically upsampled random grids."""
    value = np.zeros((size, size), np.float32)
    octaves = int(rng.integers(3, 6))
    for octave in range(octaves):
        cells = 2 ** (octave + 1)
        low = rng.random((cells, cells), dtype=np.float32)
        value += cv2.resize(low, (size, size), interpolation=cv2.INTER_CUBIC) / 2**octave
    value = (value - value.min()) / max(float(np.ptp(value)), 1e-6)
    return _to_image(value, _palette(rng, int(rng.integers(2, 5))))


def stripes(rng: np.random.Generator, size: int) -> np.ndarray:
    """Sums of one or two plane waves at random angles, wavelengths and phases."""
    yy, xx = _grid(size)
    value = np.zeros((size, size), np.float32)
    for _ in range(int(rng.integers(1, 3))):
        angle, freq = rng.uniform(0, np.pi), rng.uniform(2, 12)
        value += np.sin(2 * np.pi * freq * (np.cos(angle) * xx + np.sin(angle) * yy)
                        + rng.uniform(0, 2 * np.pi))
    value = (value - value.min()) / max(float(np.ptp(value)), 1e-6)
    return _to_image(value, _palette(rng, int(rng.integers(2, 4))))


def checker(rng: np.random.Generator, size: int) -> np.ndarray:
    """A rotated two-colour checkerboard with a random period."""
    yy, xx = _grid(size)
    angle, cells = rng.uniform(0, np.pi / 2), rng.uniform(3, 12)
    u = np.cos(angle) * xx - np.sin(angle) * yy
    v = np.sin(angle) * xx + np.cos(angle) * yy
    value = ((np.floor(u * cells) + np.floor(v * cells)) % 2).astype(np.float32)
    colours = _palette(rng, 2)
    return np.clip(colours[0] + value[..., None] * (colours[1] - colours[0]), 0, 255).astype(np.uint8)


def cells(rng: np.random.Generator, size: int) -> np.ndarray:
    """Voronoi cells of random seed points, each a flat random colour, with dark borders."""
    yy, xx = _grid(size)
    points = rng.random((int(rng.integers(6, 30)), 2), dtype=np.float32)
    dist = (yy[..., None] - points[:, 0]) ** 2 + (xx[..., None] - points[:, 1]) ** 2
    order = np.sort(dist, axis=-1)
    nearest = np.argmin(dist, axis=-1)
    image = _palette(rng, len(points))[nearest]
    border = (np.sqrt(order[..., 1]) - np.sqrt(order[..., 0])) < 0.01
    image[border] *= 0.3
    return image.astype(np.uint8)


def rings(rng: np.random.Generator, size: int) -> np.ndarray:
    """Concentric waves around a random centre, optionally twisted into a spiral."""
    yy, xx = _grid(size)
    cy, cx = rng.uniform(-0.5, 1.5, 2)
    radius = np.sqrt((yy - cy) ** 2 + (xx - cx) ** 2)
    twist = rng.uniform(-3, 3) * np.arctan2(yy - cy, xx - cx)
    value = 0.5 + 0.5 * np.sin(2 * np.pi * rng.uniform(3, 15) * radius + twist)
    return _to_image(value.astype(np.float32), _palette(rng, int(rng.integers(2, 4))))


def mondrian(rng: np.random.Generator, size: int) -> np.ndarray:
    """Overlapping axis-aligned rectangles of random colours on a random ground."""
    image = np.empty((size, size, 3), np.uint8)
    image[:] = _palette(rng, 1)[0].astype(np.uint8)
    for _ in range(int(rng.integers(5, 25))):
        y0, x0 = rng.integers(0, size, 2)
        h, w = rng.integers(size // 16 + 1, size // 2 + 2, 2)
        image[y0:y0 + h, x0:x0 + w] = _palette(rng, 1)[0].astype(np.uint8)
    return image


def lines(rng: np.random.Generator, size: int) -> np.ndarray:
    """Thin anti-aliased segments of random colour, length, width and angle over a cloudy or
    flat ground: distractors shaped like a pole or a string."""
    ground = (clouds(rng, size) if rng.random() < 0.5
              else np.full((size, size, 3), _palette(rng, 1)[0], np.uint8))
    image = np.ascontiguousarray(ground)
    for _ in range(int(rng.integers(5, 40))):
        centre = rng.uniform(0, size, 2)
        angle, half = rng.uniform(0, np.pi), rng.uniform(0.025, 0.25) * size
        offset = half * np.array([np.cos(angle), np.sin(angle)])
        ends = [tuple(int(v) for v in centre - offset), tuple(int(v) for v in centre + offset)]
        colour = tuple(float(v) for v in _palette(rng, 1)[0])
        cv2.line(image, ends[0], ends[1], colour, int(rng.integers(1, max(2, size // 32))),
                 cv2.LINE_AA)
    return image


def blobs(rng: np.random.Generator, size: int) -> np.ndarray:
    """Overlapping soft-edged rotated ellipses of random colours on a random ground: smooth
    shapes with edges at every orientation."""
    yy, xx = _grid(size)
    image = np.empty((size, size, 3), np.float32)
    image[:] = _palette(rng, 1)[0]
    for _ in range(int(rng.integers(4, 16))):
        cy, cx = rng.uniform(0, 1, 2)
        ry, rx = rng.uniform(0.03, 0.3, 2)
        angle = rng.uniform(0, np.pi)
        colour = _palette(rng, 1)[0]
        # Cover is 0 beyond sqrt(1.5) radii: only the ellipse's bounding box is computed.
        reach = np.sqrt(1.5) * max(rx, ry)
        rows = slice(max(0, int((cy - reach) * size)), min(size, int((cy + reach) * size) + 2))
        cols = slice(max(0, int((cx - reach) * size)), min(size, int((cx + reach) * size) + 2))
        dy, dx = yy[rows, cols] - cy, xx[rows, cols] - cx
        u = np.cos(angle) * dx + np.sin(angle) * dy
        v = np.cos(angle) * dy - np.sin(angle) * dx
        cover = np.clip(1.5 - (u / rx) ** 2 - (v / ry) ** 2, 0, 1)[..., None]
        image[rows, cols] = image[rows, cols] * (1 - cover) + cover * colour
    return np.clip(image, 0, 255).astype(np.uint8)


def leaves(rng: np.random.Generator, size: int) -> np.ndarray:
    """Dead leaves: opaque discs, ellipses and rotated rectangles of power-law sizes (density
    of radius r as r^-3) painted over each other until they cover the ground, in a few related
    colours, under smooth shading and a slight blur. The model reproduces the occlusion
    and scale statistics of photographs (a 1/f amplitude spectrum, edges at every scale),
    which no other family has (Lee, Mumford and Huang, 2001; Baradad et al., 2021)."""
    # A few hues, muted towards grey as most of a photograph's colours are.
    hues = _palette(rng, int(rng.integers(2, 6)))
    hues = 128 + (hues - 128) * rng.uniform(0.2, 1.0, (len(hues), 1))
    image = np.empty((size, size, 3), np.uint8)
    image[:] = hues[0].astype(np.uint8)
    # Enough leaves to cover the image several times over: with these radii a leaf covers
    # ~2 pi low^2 ln(high / low) pixels on average, ~150 at size 256.
    low, high = 0.01 * size, 0.4 * size
    count = int(rng.integers(1500, 3000))
    radii = (low ** -2 - rng.random(count) * (low ** -2 - high ** -2)) ** -0.5
    for radius in radii:
        centre = rng.uniform(-0.1, 1.1, 2) * size
        colour = np.clip(hues[rng.integers(len(hues))] * rng.uniform(0.5, 1.3)
                         + rng.normal(0, 12, 3), 0, 255)
        colour = tuple(float(v) for v in colour)
        kind = rng.integers(3)
        if kind == 0:
            cv2.circle(image, (int(centre[0]), int(centre[1])), max(1, int(radius)), colour,
                       -1, cv2.LINE_AA)
        elif kind == 1:
            axes = (max(1, int(radius)), max(1, int(radius * rng.uniform(0.3, 1.0))))
            cv2.ellipse(image, (int(centre[0]), int(centre[1])), axes,
                        float(rng.uniform(0, 180)), 0, 360, colour, -1, cv2.LINE_AA)
        else:
            box = ((float(centre[0]), float(centre[1])),
                   (float(2 * radius), float(2 * radius * rng.uniform(0.2, 1.0))),
                   float(rng.uniform(0, 180)))
            cv2.fillPoly(image, [cv2.boxPoints(box).astype(np.int32)], colour, cv2.LINE_AA)
    cells = int(rng.integers(2, 5))
    shading = cv2.resize(rng.uniform(0.6, 1.2, (cells, cells)).astype(np.float32),
                         (size, size), interpolation=cv2.INTER_CUBIC)
    shaded = image.astype(np.float32) * shading[..., None]
    sigma = rng.uniform(0.0, 0.8) * size / 256
    if sigma > 0.3:
        shaded = cv2.GaussianBlur(shaded, (0, 0), sigma)
    return np.clip(shaded, 0, 255).astype(np.uint8)


#: Texture families of each procedural bank. ``wide`` is ``train`` plus two families that
#: neither ``train`` nor ``heldout`` has, ``leaves`` is ``wide`` plus dead leaves;
#: ``heldout`` shares no family with any of them.
_TRAIN: dict[str, Generator] = {"clouds": clouds, "stripes": stripes, "checker": checker}
_WIDE: dict[str, Generator] = {**_TRAIN, "lines": lines, "blobs": blobs}
FAMILIES: dict[str, dict[str, Generator]] = {
    "train": _TRAIN,
    "wide": _WIDE,
    "leaves": {**_WIDE, "leaves": leaves},
    "heldout": {"cells": cells, "rings": rings, "mondrian": mondrian},
}


@dataclass(frozen=True)
class BackgroundBank:
    """A fixed, indexable set of square background textures; ``dr/background`` indexes it."""

    source: str
    """``train``, ``wide``, ``heldout``, or a directory path."""
    textures: np.ndarray
    """[N, S, S, 3] uint8."""
    names: tuple[str, ...]
    """One stable identifier per texture (family and seed, or file name and frame)."""

    @property
    def size(self) -> int:
        return int(self.textures.shape[1])

    def __len__(self) -> int:
        return int(self.textures.shape[0])

    def colour_grid(self, cells: int = 16) -> np.ndarray:
        """Every texture area-averaged to ``cells``² colours on a 0-1 scale:
        [N, cells, cells, 3] float32 (what camouflaged bodies take their colour from)."""
        return np.stack([cv2.resize(t, (cells, cells), interpolation=cv2.INTER_AREA)
                         for t in self.textures]).astype(np.float32) / 255.0

    def digest(self) -> str:
        """SHA-256 of the texture bytes: recorded with a dataset to detect a changed bank."""
        return hashlib.sha256(self.textures.tobytes()).hexdigest()


@functools.lru_cache(maxsize=2)
def procedural_bank(source: str, count: int, size: int, seed: int = 0) -> BackgroundBank:
    """``count`` textures of ``size``² pixels from the families of ``source`` (:data:`FAMILIES`),
    taken in turn. Kept for the process's next request of the same bank (a `quick` D's takes
    ~4.5 s to draw, and checking a bank's digest and then rendering with it asks twice), and
    on disk for the next process (:func:`bank_cache_path`): every collection's render process,
    evaluation and rebuild worker draws one. The textures are read-only, so that no user of
    the shared bank can change another's."""
    if source not in FAMILIES:
        raise ConfigError(f"procedural background source must be one of {sorted(FAMILIES)}, "
                          f"got {source!r}")
    if count < 1 or size < 1:
        raise ConfigError(f"background count and size must be >= 1, got {count} and {size}")
    families = list(FAMILIES[source].items())
    names = tuple(f"{families[i % len(families)][0]}/{seed}/{i}" for i in range(count))
    path = bank_cache_path(source, count, size, seed)
    textures = None if path is None else _read_cached(path, (count, size, size, 3))
    if textures is None:
        textures = draw_procedural(source, count, size, seed)
        if path is not None:
            _write_cached(path, textures)
    textures.setflags(write=False)
    return BackgroundBank(source, textures, names)


def draw_procedural(source: str, count: int, size: int, seed: int = 0) -> np.ndarray:
    """The textures of :func:`procedural_bank`, drawn anew: [count, size, size, 3] uint8."""
    families = list(FAMILIES[source].values())
    textures = np.empty((count, size, size, 3), np.uint8)
    for i in range(count):
        textures[i] = families[i % len(families)](np.random.default_rng([seed, i]), size)
    return textures


#: What a drawn bank depends on besides its arguments: this module's code and the libraries
#: that draw, so that a cached bank is never one that the code would no longer draw.
_DRAWN_BY = hashlib.sha256(b"\0".join([Path(__file__).read_bytes(), cv2.__version__.encode(),
                                        np.__version__.encode()])).hexdigest()[:16]


def bank_cache_path(source: str, count: int, size: int, seed: int) -> Path | None:
    """Where a drawn procedural bank is kept between processes: ``$XDG_CACHE_HOME`` (else
    ``~/.cache``) ``/twist/banks/``, named by its arguments and what draws it; None for a
    user without a home, whose processes each draw their own."""
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path("~/.cache").expanduser())
    if not root.is_absolute():
        return None
    return root / "twist" / "banks" / f"{source}-{count}-{size}-{seed}-{_DRAWN_BY}.npy"


def _read_cached(path: Path, shape: tuple[int, ...]) -> np.ndarray | None:
    try:  # mapped, not read: a process pages in the textures it draws on
        textures = np.asarray(np.load(path, mmap_mode="r", allow_pickle=False))
    except (OSError, ValueError, EOFError):  # absent, unreadable or cut short: drawn again
        return None
    return textures if textures.shape == shape and textures.dtype == np.uint8 else None


def _write_cached(path: Path, textures: np.ndarray) -> None:
    # Written aside and renamed: a process reading the same bank sees all of it or none.
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as f:
            try:
                np.save(f, textures, allow_pickle=False)
            except BaseException:  # a full disk or an interrupt: no 200 MB left behind
                Path(f.name).unlink(missing_ok=True)
                raise
        os.replace(f.name, path)
    except OSError as exc:  # a read-only home: every process draws its own
        log.debug("background bank not cached at %s: %s", path, exc)


def _square(image: np.ndarray, size: int) -> np.ndarray:
    """Centre-crop to a square and resize to ``size``² (area filter when shrinking)."""
    h, w = image.shape[:2]
    side = min(h, w)
    top, left = (h - side) // 2, (w - side) // 2
    crop = image[top:top + side, left:left + side]
    interpolation = cv2.INTER_AREA if side > size else cv2.INTER_LINEAR
    return cv2.resize(crop, (size, size), interpolation=interpolation)


def background_files(directory: str | Path) -> list[Path]:
    """The image and video files of a background folder, sorted by name; a folder that does
    not exist or holds none is refused naming it."""
    root = Path(directory)
    if not root.is_dir():
        raise BackgroundError(f"background directory {str(root)!r} does not exist or is not a folder")
    files = sorted(p for p in root.iterdir()
                   if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES + VIDEO_SUFFIXES)
    if not files:
        raise BackgroundError(f"background directory {str(root)!r} has no images or videos "
                              f"({', '.join(IMAGE_SUFFIXES + VIDEO_SUFFIXES)})")
    return files


def directory_bank(directory: str | Path, size: int, max_frames_per_video: int = 64) -> BackgroundBank:
    """Every image (and up to ``max_frames_per_video`` evenly spaced frames of every video)
    in ``directory``, sorted by file name, as ``size``² RGB textures."""
    root = Path(directory)
    files = background_files(root)
    textures, names = [], []
    for path in files:
        frames = (_video_frames(path, max_frames_per_video) if path.suffix.lower() in VIDEO_SUFFIXES
                  else _image_frames(path))
        for index, frame in frames:
            textures.append(_square(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB), size))
            names.append(f"{path.name}#{index}")
    if not textures:
        raise BackgroundError(f"no file in background directory {str(root)!r} could be read "
                              f"({len(files)} candidates)")
    log.info("loaded %d background textures from %s", len(textures), root)
    return BackgroundBank(str(root), np.stack(textures), tuple(names))


def _image_frames(path: Path) -> list[tuple[int, np.ndarray]]:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        log.warning("skipping unreadable background image %s", path)
        return []
    return [(0, image)]


def _video_frames(path: Path, limit: int) -> list[tuple[int, np.ndarray]]:
    capture = cv2.VideoCapture(str(path))
    try:
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        # Keep only evenly spaced frames while decoding, so a long video is not held in memory;
        # containers without a frame count are decoded whole and thinned afterwards.
        wanted = (set(np.linspace(0, count - 1, min(limit, count)).round().astype(int).tolist())
                  if count > 0 else None)
        frames = []
        index = 0
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            if wanted is None or index in wanted:
                frames.append((index, frame))
            index += 1
    finally:
        capture.release()
    if not frames:
        log.warning("skipping unreadable background video %s", path)
        return []
    keep = np.unique(np.linspace(0, len(frames) - 1, min(limit, len(frames))).round().astype(int))
    return [frames[i] for i in keep]


# -- background folders a user can hand to --backgrounds ------------------------------------------
#: scikit-image's bundled photographs of everyday scenes (files in its wheel's ``data``
#: folder, read directly: its loader functions may try to fetch what a wheel lacks).
SKIMAGE_PHOTOS = ("astronaut.png", "chelsea.png", "coffee.png", "motorcycle_left.png",
                  "rocket.jpg", "camera.png", "hubble_deep_field.jpg")


def shipped_photographs() -> dict[str, np.ndarray]:
    """Name -> RGB uint8 image of every photograph of everyday scenes the installed packages
    ship (matplotlib's ``grace_hopper.jpg``; with scikit-image, :data:`SKIMAGE_PHOTOS`), so
    that an evaluation in front of photographs needs no download. None may be trained on:
    they stand for the real scenes a student never saw."""
    import importlib.util

    import matplotlib.cbook

    files = [Path(matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False))]
    spec = importlib.util.find_spec("skimage")
    if spec is not None and spec.origin is not None:
        folder = Path(spec.origin).parent / "data"
        files += [folder / name for name in SKIMAGE_PHOTOS if (folder / name).is_file()]
    # IMREAD_COLOR gives three channels for grey and RGBA files alike.
    return {path.stem: cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            for path in files}


def bank_textures(bank: str, count: int, size: int, seed: int = 1) -> dict[str, np.ndarray]:
    """``count`` textures of ``size`` pixels from the families of procedural bank ``bank``
    (:data:`FAMILIES`), in turn, named ``<index>-<family>``: a bank a user can edit by hand and
    render D under (``twist-data render D D2 --backgrounds DIR``). ``seed`` 1, not the
    procedural banks' 0, so that the folder holds textures D never showed."""
    if bank not in FAMILIES:
        raise BackgroundError(f"unknown texture bank {bank!r}; valid banks are: "
                              f"{', '.join(FAMILIES)}")
    if count < 1 or size < 8:
        raise BackgroundError(f"a texture folder needs count >= 1 and size >= 8, got count "
                              f"{count} and size {size}")
    families = list(FAMILIES[bank].items())
    return {f"{i:05d}-{families[i % len(families)][0]}":
            families[i % len(families)][1](np.random.default_rng([seed, i]), size)
            for i in range(count)}


def write_background_folder(out: str | Path, images: Mapping[str, np.ndarray]) -> list[Path]:
    """Write RGB uint8 ``images`` as ``<name>.png`` into the new folder ``out``, whole or not
    at all: an existing ``out`` is refused naming it, and the files are written into a
    temporary sibling renamed at the end."""
    out = Path(out)
    if out.exists():
        raise BackgroundError(f"{str(out)!r} already exists; a background folder is written "
                              f"into a new folder")
    partial = out.with_name(f".{out.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    try:
        for name, image in images.items():
            if not cv2.imwrite(str(partial / f"{name}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
                raise BackgroundError(f"could not write {name}.png into {str(out)!r}")
        partial.rename(out)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return sorted(out.iterdir())
