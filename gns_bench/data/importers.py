"""Importers from other projects' layouts into ours, without TensorFlow.

deepmind  the original `learning_to_simulate` release: `{train,valid,test}.tfrecord` holding
          `tf.train.SequenceExample`s (context `particle_type`: int64 bytes; sequence `position`:
          float32 bytes per frame, [N * D]; optional sequence `step_context`) + `metadata.json`.
          Read with the `tfrecord` package.
npz       geoelements/gns: `{train,valid,test}.npz`, each entry a trajectory stored as an object
          array (positions [T, N, D], particle_type [N] [, material property]) + `metadata.json`
          (flat, or with the fields under a `train` key).

Both validate everything through the loader before the dataset is renamed into place.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from gns_bench.data.format import (
    SPLITS,
    DatasetError,
    DatasetWriter,
    Metadata,
    Trajectory,
)

# Splits an importer must find; a missing valid or test split is an error, not silently skipped.
_REQUIRED = SPLITS


def _read_source_metadata(src: Path) -> dict[str, Any]:
    path = src / "metadata.json"
    if not path.is_file():
        raise DatasetError(path, "no such file: the source dataset needs its metadata.json")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DatasetError(path, f"unreadable JSON: {exc}") from exc
    if isinstance(data.get("train"), dict) and "dim" in data["train"]:  # geoelements' nested layout
        data = data["train"]
    return data


def _finish(writer: DatasetWriter, raw_meta: dict[str, Any], src: Path, name: str, importer: str,
            types_seen: set[int]) -> Path:
    meta = Metadata.from_json(dict(raw_meta), src / "metadata.json")
    meta.name = meta.name or name
    if not meta.particle_types:
        meta.particle_types = {f"type_{t}": t for t in sorted(types_seen)}
    meta.generator = {"name": "gns-bench import", "importer": importer, "source": str(src)}
    return writer.finish(meta)


def _tfrecord_trajectories(path: Path, dim: int) -> Iterator[Trajectory]:
    from tfrecord.reader import sequence_loader

    try:
        records = sequence_loader(str(path), None)  # no descriptions: every feature present is returned
        for index, (context, sequence) in enumerate(records):
            key = f"{index:05d}"
            if "particle_type" not in context:
                raise DatasetError(path, "missing context feature", key, "particle_type")
            raw_types = context["particle_type"]
            types = np.frombuffer(bytes(raw_types), dtype=np.int64).copy()
            frames = sequence.get("position")
            if not frames:
                raise DatasetError(path, "missing sequence feature", key, "position")
            flat = [np.frombuffer(bytes(f), dtype=np.float32) for f in frames]
            size = flat[0].size
            if any(f.size != size for f in flat) or size % dim or size // dim != types.size:
                raise DatasetError(path, f"frames of {sorted({f.size for f in flat})} floats do not make "
                                   f"[N={types.size}, D={dim}]", key, "position")
            position = np.stack(flat).reshape(len(flat), types.size, dim)
            step_context = None
            if sequence.get("step_context"):
                step_context = np.stack([np.frombuffer(bytes(c), dtype=np.float32)
                                         for c in sequence["step_context"]])
            yield Trajectory(position, types, step_context)
    except DatasetError:
        raise
    except Exception as exc:  # truncated record, bad protobuf
        raise DatasetError(path, f"unreadable or truncated TFRecord file ({type(exc).__name__}: {exc})") from exc


def import_deepmind(src: str | Path, dst: str | Path, *, overwrite: bool = False) -> Path:
    src = Path(src)
    dim = Metadata.from_json(_read_source_metadata(src), src / "metadata.json").dim
    return _import(src, dst, overwrite, "tfrecord", lambda path: _tfrecord_trajectories(path, dim), "deepmind")


def _npz_trajectories(path: Path) -> Iterator[Trajectory]:
    try:
        archive = np.load(path, allow_pickle=True)  # the layout stores object arrays: trusted input only
    except Exception as exc:
        raise DatasetError(path, f"unreadable npz file ({exc})") from exc
    with archive:
        for key in archive.files:
            try:
                item = archive[key]
            except Exception as exc:
                raise DatasetError(path, f"unreadable entry ({exc})", key) from exc
            if item.dtype != object or item.ndim != 1 or len(item) < 2:
                raise DatasetError(path, "expected an object array (positions, particle_type[, material])",
                                   key)
            position, types = np.asarray(item[0]), np.asarray(item[1])
            if not np.issubdtype(position.dtype, np.floating):
                raise DatasetError(path, f"expected floats, got {position.dtype}", key, "position")
            if not np.issubdtype(types.dtype, np.integer):
                raise DatasetError(path, f"expected integers, got {types.dtype}", key, "particle_type")
            yield Trajectory(position.astype(np.float32), types.astype(np.int64))


def import_npz(src: str | Path, dst: str | Path, *, overwrite: bool = False) -> Path:
    return _import(Path(src), dst, overwrite, "npz", _npz_trajectories, "npz")


def _import(src: Path, dst: str | Path, overwrite: bool, suffix: str,
            read: Callable[[Path], Iterator[Trajectory]], importer: str) -> Path:
    """Copy every split's trajectories into a new dataset; an interrupted import resumes where it stopped."""
    raw = _read_source_metadata(src)
    writer = DatasetWriter(dst, overwrite=overwrite)
    types_seen: set[int] = set()
    for split in _REQUIRED:
        path = src / f"{split}.{suffix}"
        if not path.is_file():
            raise DatasetError(path, "no such file")
        skipped = writer.count(split)
        for index, traj in enumerate(read(path)):
            types_seen.update(np.unique(traj.particle_type).tolist())
            if index >= skipped:
                writer.add(split, traj)
    return _finish(writer, raw, src, src.name, importer, types_seen)
