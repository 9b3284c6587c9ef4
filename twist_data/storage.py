"""Zarr v3 specifics: how arrays are chunked and compressed, and a fast reader of image frames.

Images are stored with the zarr v3 sharding codec: one file holds ``steps_per_file`` steps of
all K views, split into inner chunks of one view of one step. Per-step inner chunks are what
random windows with a random view per step need: a window of L steps decodes exactly L frames.
Domain randomisation re-samples the background every step, so there is no temporal redundancy
that larger chunks could compress away.

zarr-python's own path costs about 0.6 ms per inner chunk here (async machinery per chunk),
i.e. ~17 windows/s when reading and ~0.7 s per 500-step episode when writing.
:class:`FrameFile` therefore reads inner chunks directly, following the sharding spec (an index
of ``(offset, nbytes)`` uint64 pairs plus a CRC32C at the end of the file), and decodes them
with the same numcodecs codec zarr uses; :class:`FrameWriter` writes shard files the same way.
Both are only used when the array's metadata is exactly the layout they understand; otherwise
readers and writers fall back to zarr, and the files stay readable by any zarr v3 reader.
"""

from __future__ import annotations

import mmap
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import google_crc32c
import numpy as np
import zarr
from numcodecs import blosc as _blosc
from numcodecs import zstd as _zstd
from zarr.codecs import BloscCodec, Crc32cCodec, ShardingCodec, ZstdCodec

from twist_data.errors import DatasetCorruptError

ImageCodec = Literal["blosc-lz4", "zstd", "none"]
_EMPTY = 2**64 - 1  # the sharding spec's marker for an inner chunk that was never written


@dataclass(frozen=True)
class StorageLayout:
    """How a shard's arrays are chunked and compressed (stored in every shard)."""

    steps_per_file: int = 1000
    """Steps per image shard file and per low-dimensional chunk (files per array per steps)."""
    image_codec: ImageCodec = "blosc-lz4"
    """Compressor of image inner chunks: blosc-lz4 decodes ~2.5x faster than zstd for ~the same
    ratio on 64x64 renders."""
    image_level: int = 5
    """Compression level of the image codec."""
    lowdim_level: int = 3
    """zstd level of every other array."""
    episodes_per_chunk: int = 4096
    """Chunk length of the per-episode arrays under ``meta/``."""
    checksums: bool = True
    """A CRC32C after every chunk of every array and after every image frame (zarr's
    ``crc32c`` codec, which any zarr v3 reader checks), so that a flipped byte is found where
    it is read. Shards of format version 1 have none."""

    def __post_init__(self) -> None:
        if self.steps_per_file < 1:
            raise ValueError(f"steps_per_file must be >= 1, got {self.steps_per_file}")
        if self.image_codec not in ("blosc-lz4", "zstd", "none"):
            raise ValueError(
                f"unknown image_codec {self.image_codec!r}; valid: blosc-lz4, zstd, none"
            )
        if self.episodes_per_chunk < 1:
            raise ValueError(f"episodes_per_chunk must be >= 1, got {self.episodes_per_chunk}")

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> StorageLayout:
        """A stored layout; one written before checksums existed has none."""
        return cls(**{"checksums": False, **data})


def _checksum(layout: StorageLayout) -> list[Any]:
    return [Crc32cCodec()] if layout.checksums else []


def _image_compressors(layout: StorageLayout) -> list[Any]:
    if layout.image_codec == "blosc-lz4":
        compressors: list[Any] = [BloscCodec(cname="lz4", clevel=layout.image_level,
                                             shuffle="noshuffle", typesize=1)]
    elif layout.image_codec == "zstd":
        compressors = [ZstdCodec(level=layout.image_level)]
    else:
        compressors = []
    return compressors + _checksum(layout)


def create_step_array(group: zarr.Group, name: str, dtype: str, trailing: tuple[int, ...],
                      layout: StorageLayout, sharded_frames: bool) -> zarr.Array:
    """Create an empty per-step array ``[0, *trailing]`` chunked along time."""
    spf = layout.steps_per_file
    config = {"write_empty_chunks": True}
    if sharded_frames:
        # trailing = (K, H, W, C): one inner chunk per view per step, one file per spf steps.
        return group.create_array(
            name, shape=(0, *trailing), dtype=dtype, shards=(spf, *trailing),
            chunks=(1, 1, *trailing[1:]), compressors=_image_compressors(layout),
            fill_value=0, config=config,
        )
    return group.create_array(
        name, shape=(0, *trailing), dtype=dtype, chunks=(spf, *trailing),
        compressors=[ZstdCodec(level=layout.lowdim_level), *_checksum(layout)], fill_value=0,
        config=config,
    )


def create_episode_array(group: zarr.Group, name: str, dtype: str, trailing: tuple[int, ...],
                         layout: StorageLayout) -> zarr.Array:
    """Create an empty per-episode array ``[0, *trailing]``."""
    return group.create_array(
        name, shape=(0, *trailing), dtype=dtype, chunks=(layout.episodes_per_chunk, *trailing),
        compressors=[ZstdCodec(level=layout.lowdim_level), *_checksum(layout)], fill_value=0,
        config={"write_empty_chunks": True},
    )


Decoder = Callable[[memoryview, np.ndarray], None]


def _decode_blosc(src: memoryview, dest: np.ndarray) -> None:
    _blosc.decompress(src, dest)


def _decode_zstd(src: memoryview, dest: np.ndarray) -> None:
    dest.reshape(-1)[:] = np.frombuffer(_zstd.decompress(src), dtype=dest.dtype)


def _decode_raw(src: memoryview, dest: np.ndarray) -> None:
    dest.reshape(-1)[:] = np.frombuffer(src, dtype=dest.dtype)


def _frame_codecs(array: zarr.Array) -> list[dict[str, Any]] | None:
    """The inner codecs of a sharded frame array, or None if its layout is not the known one.

    Known layout: a single ``sharding_indexed`` codec whose inner chunk is one frame
    ``(1, 1, H, W, C)``, inner codecs ``bytes`` + optional blosc/zstd + optional ``crc32c``,
    index ``bytes(little)`` + ``crc32c`` at the end, and the default ``/`` chunk-key
    encoding.
    """
    meta = array.metadata
    codecs = getattr(meta, "codecs", ())
    if len(codecs) != 1 or not isinstance(codecs[0], ShardingCodec) or array.dtype != np.uint8:
        return None
    sharding = codecs[0].to_dict()["configuration"]
    if tuple(sharding["chunk_shape"]) != (1, 1, *array.shape[2:]):
        return None
    index = [c["name"] if isinstance(c, dict) else c.to_dict()["name"]
             for c in sharding["index_codecs"]]
    if index != ["bytes", "crc32c"] or str(sharding["index_location"]).split(".")[-1] != "end":
        return None
    if meta.chunk_key_encoding.to_dict().get("configuration", {}).get("separator", "/") != "/":
        return None
    inner = [c if isinstance(c, dict) else c.to_dict() for c in sharding["codecs"]]
    names = [c["name"] for c in inner]
    if names[-1:] == ["crc32c"]:
        names = names[:-1]
    if names not in (["bytes"], ["bytes", "blosc"], ["bytes", "zstd"]):
        return None
    return inner


class FrameChecksumError(ValueError):
    """A frame's bytes do not match the CRC32C stored after them."""


#: A frame whose encoded bytes are under 1/BLACK_RATIO of its pixels' is looked at for zeros.
BLACK_RATIO = 16


class FrameBlackError(ValueError):
    """A frame of a D drawn by twist is all zeros (:attr:`FrameReader.refuse_black`)."""


def frame_decoder(array: zarr.Array) -> tuple[Decoder, bool] | None:
    """The direct decoder of one frame's payload of a sharded frame array, and whether each
    stored frame ends in a CRC32C of its payload; None if the layout is not the known one
    (see :func:`_frame_codecs`)."""
    inner = _frame_codecs(array)
    if inner is None:
        return None
    checksum = inner[-1]["name"] == "crc32c"
    codec = inner[-2] if checksum else inner[-1]
    decode = {"bytes": _decode_raw, "blosc": _decode_blosc, "zstd": _decode_zstd}[codec["name"]]
    return decode, checksum


Encoder = Callable[[np.ndarray], bytes]
_SHUFFLES = {"noshuffle": _blosc.NOSHUFFLE, "shuffle": _blosc.SHUFFLE,
             "bitshuffle": _blosc.BITSHUFFLE}


def frame_encoder(array: zarr.Array) -> Encoder | None:
    """The direct encoder of one frame ``[H, W, C]`` with the array's own codec settings; None
    if the layout is not the known one (see :func:`_frame_codecs`)."""
    inner = _frame_codecs(array)
    if inner is None:
        return None
    checksum = inner[-1]["name"] == "crc32c"
    codec = inner[-2] if checksum else inner[-1]
    settings = codec.get("configuration", {})
    if codec["name"] == "blosc":
        shuffle = settings.get("shuffle", "noshuffle")
        if shuffle not in _SHUFFLES:
            return None
        cname = str(settings.get("cname", "lz4")).encode()
        clevel, blocksize = int(settings.get("clevel", 5)), int(settings.get("blocksize", 0))

        def encode(frame: np.ndarray) -> bytes:
            return _blosc.compress(frame, cname, clevel, _SHUFFLES[shuffle], blocksize, 1)
    elif codec["name"] == "zstd":
        level = int(settings.get("level", 0))

        def encode(frame: np.ndarray) -> bytes:
            return _zstd.compress(frame, level)
    else:
        def encode(frame: np.ndarray) -> bytes:
            return frame.tobytes()
    if not checksum:
        return encode

    def encode_checked(frame: np.ndarray) -> bytes:
        data = encode(frame)
        return data + google_crc32c.value(data).to_bytes(4, "little")
    return encode_checked


def shard_file(array: zarr.Array, array_dir: Path, index: int) -> Path:
    """The file of image shard ``index`` (steps ``index * steps_per_file`` onwards)."""
    return array_dir / array.metadata.encode_chunk_key((index, 0, 0, 0, 0))


class FrameFile:
    """One image shard file, memory-mapped, with its parsed inner-chunk index.

    A writer replaces shard files atomically (write then rename), so a mapping stays a
    consistent snapshot of the file as it was when opened.
    """

    def __init__(self, path: Path, n_inner: int) -> None:
        self.path = path
        try:
            with open(path, "rb") as f:
                size = os.fstat(f.fileno()).st_size
                index_bytes = n_inner * 16 + 4
                if size < index_bytes:
                    raise DatasetCorruptError(
                        f"image shard file {path} is truncated: {size} bytes, "
                        f"its index alone needs {index_bytes}"
                    )
                self._mmap = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except FileNotFoundError:
            raise DatasetCorruptError(f"image shard file {path} is missing") from None
        self.view = memoryview(self._mmap)
        raw = self.view[size - index_bytes: size - 4]
        stored_crc = int.from_bytes(self.view[size - 4:size], "little")
        if google_crc32c.value(bytes(raw)) != stored_crc:
            raise DatasetCorruptError(f"image shard file {path} has a corrupt index (CRC32C mismatch)")
        pairs = np.frombuffer(raw, dtype="<u8").reshape(n_inner, 2)
        # Python ints index faster than NumPy scalars in the per-frame loop.
        self.offsets: list[int] = pairs[:, 0].tolist()
        self.nbytes: list[int] = pairs[:, 1].tolist()
        self.size = size

    def close(self) -> None:
        self.view.release()
        self._mmap.close()


class FrameCorruptError(DatasetCorruptError):
    """A stored frame cannot be decoded; ``step`` is its step within the shard."""

    def __init__(self, message: str, step: int) -> None:
        super().__init__(message)
        self.step = step


def reason(exc: BaseException) -> str:
    """A codec or zarr error as a short phrase: its type and first line (zarr's checksum
    mismatch, which quotes both checksums' bytes, as ``CRC32C mismatch``)."""
    text = str(exc).strip().splitlines()
    if isinstance(exc, FrameChecksumError) or (text and "checksum do not match" in text[0]):
        return "CRC32C mismatch"
    if isinstance(exc, FrameBlackError):
        return text[0]
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


class FrameReader:
    """Decodes single frames ``[H, W, C]`` of one sharded image array straight from its files.

    With ``checksum``, each frame's CRC32C is checked the first time this reader decodes it:
    the check costs about a third of decoding a 64x64 render (the CRC needs a copy of the
    bytes and a Python call per frame), and training reads every frame many times, while a
    file replaced under a reader is remapped (and rechecked) only by a new reader."""

    def __init__(self, array: zarr.Array, array_dir: Path, decoder: Decoder,
                 steps_per_file: int, checksum: bool = False, refuse_black: bool = False
                 ) -> None:
        self.array = array
        self.array_dir = array_dir
        self.decoder = decoder
        self.checksum = checksum
        #: Refuse a frame of zeros (checked with the CRC32C, the first time a frame is read):
        #: twist's renderer draws none, so one in its D was overwritten under a valid checksum.
        self.refuse_black = refuse_black
        self._checked = bytearray(int(array.shape[0]) * int(array.shape[1]))
        self.views = int(array.shape[1])
        self.steps_per_file = steps_per_file
        self._files: dict[int, FrameFile] = {}
        self._pid = os.getpid()

    def _file(self, index: int) -> FrameFile:
        if self._pid != os.getpid():  # forked into a DataLoader worker: never share mappings
            self._files = {}
            self._pid = os.getpid()
        f = self._files.get(index)
        if f is None:
            f = FrameFile(shard_file(self.array, self.array_dir, index),
                          self.steps_per_file * self.views)
            self._files[index] = f
        return f

    def read_into(self, steps: np.ndarray, views: np.ndarray, out: np.ndarray,
                  rows: np.ndarray) -> None:
        """Decode frame ``(steps[i], views[i])`` into ``out[rows[i]]``; out: [n, H, W, C]."""
        spf, k, decode = self.steps_per_file, self.views, self.decoder
        checksum, checked = self.checksum, self._checked
        for row, t, v in zip(rows.tolist(), steps.tolist(), views.tolist(), strict=True):
            try:
                f = self._file(t // spf)
            except FrameCorruptError:
                raise
            except DatasetCorruptError as exc:  # a missing, truncated or badly indexed file
                raise FrameCorruptError(str(exc), t) from None
            j = (t % spf) * k + v
            off, nb = f.offsets[j], f.nbytes[j]
            if off == _EMPTY:
                if self.refuse_black:  # an inner chunk zarr dropped as all zeros
                    raise FrameCorruptError(f"image shard file {f.path}: the frame of step {t} "
                                            f"view {v} cannot be decoded (it is all zeros, "
                                            "which no render draws)", t)
                out[row] = 0
                continue
            if off + nb > f.size:
                raise FrameCorruptError(f"image shard file {f.path}: the frame of step {t} "
                                        f"view {v} points past the end of the file", t)
            try:
                first = False
                if checksum:
                    nb -= 4
                    key = t * k + v
                    first = key >= len(checked) or not checked[key]
                    if first:
                        stored = int.from_bytes(f.view[off + nb: off + nb + 4], "little")
                        if nb < 0 or google_crc32c.value(bytes(f.view[off: off + nb])) != stored:
                            raise FrameChecksumError("CRC32C mismatch")
                decode(f.view[off: off + nb], out[row])
                if first:
                    # Only a frame that compressed to a sliver can be all zeros: a render
                    # never does, and looking at every frame would cost a fifth more.
                    if (self.refuse_black and nb * BLACK_RATIO < out[row].nbytes
                            and not out[row].any()):
                        raise FrameBlackError("it is all zeros, which no render draws")
                    if key < len(checked):
                        checked[key] = 1
            except Exception as exc:  # blosc, zstd and the checksum raise assorted types
                raise FrameCorruptError(f"image shard file {f.path}: the frame of step {t} "
                                        f"view {v} cannot be decoded ({reason(exc)})", t
                                        ) from None

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        self._files = {}


class FrameWriter:
    """Appends frames to a sharded image array by writing its shard files directly.

    zarr-python encodes inner chunks through its async pipeline at ~0.6 ms each, which made
    writing 28% of collection time; this writer encodes with the same numcodecs codec and
    builds each shard file (chunks, then the ``(offset, nbytes)`` index and its CRC32C) itself.
    A file is written as ``<name>.partial`` and renamed into place, as zarr's store does, so
    a kill leaves the old or the new file. The array's shape must already cover the frames
    (the caller resizes it through zarr, which owns the metadata).
    """

    def __init__(self, array: zarr.Array, array_dir: Path, encoder: Encoder,
                 steps_per_file: int) -> None:
        self.array, self.array_dir, self.encoder = array, array_dir, encoder
        self.steps_per_file = steps_per_file
        self.views = int(array.shape[1])

    def append(self, start: int, frames: np.ndarray) -> None:
        """Write ``frames`` [T, K, H, W, C] as steps ``start .. start + T - 1``. Frames of
        those steps and later ones already in the files (an uncommitted attempt) are replaced."""
        spf, k = self.steps_per_file, self.views
        stop = start + len(frames)
        for file_index in range(start // spf, (stop - 1) // spf + 1):
            first = max(start, file_index * spf)
            last = min(stop, (file_index + 1) * spf)
            path = shard_file(self.array, self.array_dir, file_index)
            kept = self._kept_chunks(path, (first - file_index * spf) * k)
            entries = kept + [self.encoder(np.ascontiguousarray(frames[t - start, v]))
                              for t in range(first, last) for v in range(k)]
            chunks = [c for c in entries if c is not None]
            offsets = np.full((spf * k, 2), _EMPTY, dtype="<u8")
            position = 0
            for j, chunk in enumerate(entries):
                if chunk is not None:
                    offsets[j] = (position, len(chunk))
                    position += len(chunk)
            index = offsets.tobytes()
            crc = google_crc32c.value(index).to_bytes(4, "little")
            path.parent.mkdir(parents=True, exist_ok=True)
            partial = path.with_name(path.name + ".partial")
            with open(partial, "wb") as f:
                f.writelines([*chunks, index, crc])
            os.replace(partial, path)

    def _kept_chunks(self, path: Path, count: int) -> list[bytes | None]:
        """The encoded first ``count`` inner chunks of an existing shard file (None: never
        written)."""
        if count == 0 or not path.exists():
            return [None] * count
        frame_file = FrameFile(path, self.steps_per_file * self.views)
        try:
            return [bytes(frame_file.view[off: off + nb]) if off != _EMPTY else None
                    for off, nb in zip(frame_file.offsets[:count], frame_file.nbytes[:count],
                                       strict=True)]
        finally:
            frame_file.close()
