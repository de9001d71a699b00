"""The on-disk dataset format: one directory holding `metadata.json` and `train.h5`, `valid.h5`, `test.h5`.

Each h5 file has one group per trajectory (`00000`, `00001`, ...) with
  position       [T, N, D] float32  (T = sequence_length + 1 frames)
  particle_type  [N]       int64
  step_context   [T, C]    float32  (optional: global context such as a friction angle)
  birth_step     [N]       int64    (optional: inflow; the frame each particle enters the scene)
which is also the layout LagrangeBench reads. `metadata.json` holds the fields of the original
DeepMind release plus ours (name, particle types, walls, gravity, generator, content hash).

Loading validates everything before returning anything; every problem is a `DatasetError` naming the
file, the trajectory and the field.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

SPLITS = ("train", "valid", "test")
REQUIRED_FIELDS = ("position", "particle_type")
OPTIONAL_FIELDS = ("step_context", "birth_step")

# Particle type ids as in the released data (9 possible ids: NUM_PARTICLE_TYPES in DeepMind's
# learning_to_simulate/train.py). Id 3 is kinematic: boundaries and obstacles, in the graph but never
# predicted, noised or in the loss.
NUM_PARTICLE_TYPES = 9
KINEMATIC_PARTICLE_TYPE = 3
RIGID_PARTICLE_TYPE = 0  # a rigid body's particles (BOXBATH's cube): reports measure its rigidity
PARTICLE_TYPE_NAMES = {3: "kinematic", 5: "water", 6: "sand", 7: "goop", 0: "rigid"}
# One colour per particle type for every picture gns-bench draws (datasets, rollouts, reports).
PARTICLE_TYPE_COLOURS = {5: "#2b7bba", 6: "#d9a441", 7: "#b0378f", 3: "#555555", 0: "#d62728"}
OTHER_TYPE_COLOUR = "#333333"  # a type without a colour of its own

# Data may stray outside `bounds` by this fraction of the largest bound span before it is rejected.
DEFAULT_BOUNDS_TOLERANCE = 0.05


def type_colour(particle_type: int) -> str:
    return PARTICLE_TYPE_COLOURS.get(int(particle_type), OTHER_TYPE_COLOUR)


def type_colours(particle_type: Iterable[int]) -> list[str]:
    return [type_colour(t) for t in particle_type]


class DatasetError(ValueError):
    """Bad dataset input. The message names the file, the trajectory and the field."""

    def __init__(self, path: str | os.PathLike, problem: str, trajectory: str | None = None,
                 field: str | None = None):
        where = str(path)
        if trajectory is not None:
            where += f", trajectory {trajectory}"
        if field is not None:
            where += f", field '{field}'"
        super().__init__(f"{where}: {problem}")
        self.path, self.trajectory, self.field = str(path), trajectory, field


@dataclass
class Trajectory:
    """One simulated trajectory."""

    position: np.ndarray  # [T, N, D] float32
    particle_type: np.ndarray  # [N] int64
    step_context: np.ndarray | None = None  # [T, C] float32
    # Inflow: the frame at which each particle enters the scene (None: all present from frame 0). Before
    # that frame its positions are its prescribed path (the emitter's), which give a particle entering at
    # frame b its velocity history; the model sees it only from frame b on (evaluate/rollout.py).
    birth_step: np.ndarray | None = None  # [N] int64

    @property
    def has_inflow(self) -> bool:
        return self.birth_step is not None and bool(np.any(self.birth_step > 0))

    def active(self, frame: int) -> np.ndarray:
        """[N] bool: the particles present at `frame`."""
        if self.birth_step is None:
            return np.ones(self.num_particles, dtype=bool)
        return self.birth_step <= frame

    def select(self, mask: np.ndarray) -> Trajectory:
        """The trajectory of the particles in `mask` only."""
        return Trajectory(self.position[:, mask], self.particle_type[mask], self.step_context,
                          None if self.birth_step is None else self.birth_step[mask])

    @property
    def num_steps(self) -> int:
        return self.position.shape[0]

    @property
    def num_particles(self) -> int:
        return self.position.shape[1]


@dataclass
class Metadata:
    """`metadata.json`: the paper's fields, then ours. Unknown keys are kept in `extra`."""

    bounds: list[list[float]]
    sequence_length: int
    default_connectivity_radius: float
    dim: int
    dt: float
    vel_mean: list[float]
    vel_std: list[float]
    acc_mean: list[float]
    acc_std: list[float]
    context_mean: list[float] | None = None
    context_std: list[float] | None = None
    # Ours.
    name: str = ""
    particle_types: dict[str, int] = field(default_factory=dict)  # name -> id, the types this dataset uses
    walls: bool = True  # whether the bounds are walls (wall-distance node features)
    gravity: list[float] | None = None  # gravity per stored step squared (for the gravity-bias ablation)
    generator: dict[str, Any] | None = None
    content_hash: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def num_particle_types(self) -> int:
        return len(self.particle_types)

    @property
    def context_size(self) -> int:
        return len(self.context_mean) if self.context_mean is not None else 0

    def to_json(self) -> dict[str, Any]:
        out = {k: v for k, v in dataclasses.asdict(self).items() if k != "extra" and v is not None}
        out.update(self.extra)
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any], path: str | os.PathLike = "metadata.json") -> Metadata:
        names = {f.name for f in dataclasses.fields(cls)} - {"extra"}
        required = [f.name for f in dataclasses.fields(cls)
                    if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
        for key in required:
            if key not in data:
                raise DatasetError(path, f"missing key '{key}' (required: {', '.join(required)})", field=key)
        known = {k: v for k, v in data.items() if k in names}
        meta = cls(**known, extra={k: v for k, v in data.items() if k not in names})
        meta.validate(path)
        return meta

    def validate(self, path: str | os.PathLike = "metadata.json") -> None:
        """Every field's type and range, the first problem a `DatasetError` naming the field (one schema: this)."""
        def fail(key: str, expected: str) -> None:
            raise DatasetError(path, f"expected {expected}, got {getattr(self, key)!r}", field=key)

        def number(value: Any) -> bool:  # a JSON number (bools are ints in Python, not numbers here)
            return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

        def numbers(value: Any, count: int | None = None) -> bool:
            return (isinstance(value, list) and all(number(v) for v in value)
                    and (count is None or len(value) == count))

        if not (isinstance(self.dim, int) and not isinstance(self.dim, bool) and self.dim in (2, 3)):
            fail("dim", "2 or 3")
        if not (isinstance(self.bounds, list) and len(self.bounds) == self.dim
                and all(numbers(pair, 2) and pair[0] < pair[1] for pair in self.bounds)):
            fail("bounds", f"{self.dim} pairs of numbers [lo, hi] with lo < hi")
        if not (isinstance(self.sequence_length, int) and not isinstance(self.sequence_length, bool)
                and self.sequence_length > 0):
            fail("sequence_length", "a positive integer")
        if not (number(self.default_connectivity_radius) and self.default_connectivity_radius > 0):
            fail("default_connectivity_radius", "a positive number")
        if not (number(self.dt) and self.dt > 0):
            fail("dt", "a positive number (seconds between stored frames)")
        for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
            if not numbers(getattr(self, key), self.dim):
                fail(key, f"a list of {self.dim} finite numbers")
        for key in ("vel_std", "acc_std"):
            if any(v < 0 for v in getattr(self, key)):
                fail(key, "non-negative standard deviations")
        if (self.context_mean is None) != (self.context_std is None):
            fail("context_std", "context_mean and context_std both present or both absent")
        if self.context_mean is not None:
            if not numbers(self.context_mean):
                fail("context_mean", "a list of finite numbers")
            if not numbers(self.context_std, len(self.context_mean)) or any(v < 0 for v in self.context_std):
                fail("context_std", f"{len(self.context_mean)} non-negative numbers, as many as context_mean")
        if not isinstance(self.name, str):
            fail("name", "a string")
        if not isinstance(self.particle_types, dict):
            fail("particle_types", "an object {name: id}")
        for name, type_id in self.particle_types.items():
            if not (isinstance(type_id, int) and not isinstance(type_id, bool) and 0 <= type_id < NUM_PARTICLE_TYPES):
                raise DatasetError(path, f"particle type '{name}' has id {type_id!r}, expected an integer "
                                   f"in [0, {NUM_PARTICLE_TYPES})", field="particle_types")
        if not isinstance(self.walls, bool):
            fail("walls", "true or false")
        if self.gravity is not None and not numbers(self.gravity, self.dim):
            fail("gravity", f"a list of {self.dim} finite numbers")
        if self.generator is not None and not isinstance(self.generator, dict):
            fail("generator", "an object")
        if self.content_hash is not None and not (isinstance(self.content_hash, str) and len(self.content_hash) == 64
                                                  and all(c in "0123456789abcdef" for c in self.content_hash)):
            fail("content_hash", "a SHA-256 as 64 lowercase hex digits")


def read_metadata(dataset_dir: str | os.PathLike) -> Metadata:
    path = Path(dataset_dir) / "metadata.json"
    if not path.is_file():
        raise DatasetError(path, "no such file (is this a dataset directory?)")
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(path, f"unreadable JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise DatasetError(path, "expected a JSON object at the top level")
    return Metadata.from_json(data, path)


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, path)


# ----------------------------------------------------------------------------------------------
# Reading and validation
# ----------------------------------------------------------------------------------------------

def validate_trajectory(traj: Trajectory, meta: Metadata, path: str | os.PathLike, key: str, *,
                        min_length: int, bounds_tolerance: float = DEFAULT_BOUNDS_TOLERANCE) -> None:
    """Raise `DatasetError` for the first problem found in one trajectory."""
    pos, types = traj.position, traj.particle_type
    if pos.ndim != 3:
        raise DatasetError(path, f"expected rank 3 [T, N, D], got shape {pos.shape}", key, "position")
    if pos.shape[2] != meta.dim:
        raise DatasetError(path, f"expected dim D={meta.dim} (metadata 'dim'), got shape {pos.shape}",
                           key, "position")
    if pos.shape[0] < min_length:
        raise DatasetError(path, f"T={pos.shape[0]} frames is shorter than the {min_length} frames "
                           "one training window needs", key, "position")
    if pos.shape[0] != meta.sequence_length + 1:
        raise DatasetError(path, f"T={pos.shape[0]} frames, but metadata 'sequence_length' {meta.sequence_length} "
                           f"says every trajectory holds sequence_length + 1 = {meta.sequence_length + 1}", key,
                           "position")
    if pos.shape[1] == 0:
        raise DatasetError(path, "no particles (N=0)", key, "position")
    if types.ndim != 1 or types.shape[0] != pos.shape[1]:
        raise DatasetError(path, f"expected shape [N]=[{pos.shape[1]}], got {types.shape}", key,
                           "particle_type")
    if not np.all(np.isfinite(pos)):
        t, n, _ = np.argwhere(~np.isfinite(pos))[0]
        raise DatasetError(path, f"NaN or inf (first at frame {t}, particle {n})", key, "position")
    allowed = set(meta.particle_types.values()) if meta.particle_types else set(range(NUM_PARTICLE_TYPES))
    present = set(np.unique(types).tolist())
    if not present <= allowed:
        raise DatasetError(path, f"particle types {sorted(present - allowed)} are not among the declared "
                           f"types {sorted(allowed)} (metadata 'particle_types')", key, "particle_type")
    bounds = np.asarray(meta.bounds, dtype=np.float64)
    tol = bounds_tolerance * float(np.max(bounds[:, 1] - bounds[:, 0]))
    lo, hi = pos.min(axis=(0, 1)), pos.max(axis=(0, 1))
    if np.any(lo < bounds[:, 0] - tol) or np.any(hi > bounds[:, 1] + tol):
        raise DatasetError(path, f"positions span [{lo.tolist()}, {hi.tolist()}], outside the metadata "
                           f"bounds {bounds.tolist()} by more than {tol:.3g}", key, "position")
    ctx = traj.step_context
    if meta.context_size and ctx is None:
        raise DatasetError(path, "missing: metadata declares a global context (context_mean)", key,
                           "step_context")
    if ctx is not None:
        if ctx.ndim != 2 or ctx.shape[0] != pos.shape[0]:
            raise DatasetError(path, f"expected shape [T, C] with T={pos.shape[0]}, got {ctx.shape}", key,
                               "step_context")
        if meta.context_size and ctx.shape[1] != meta.context_size:
            raise DatasetError(path, f"expected C={meta.context_size} (metadata context_mean), got "
                               f"{ctx.shape[1]}", key, "step_context")
        if not np.all(np.isfinite(ctx)):
            raise DatasetError(path, "NaN or inf", key, "step_context")
    birth = traj.birth_step
    if birth is not None:
        if birth.shape != (pos.shape[1],):
            raise DatasetError(path, f"expected shape [N]=[{pos.shape[1]}], got {birth.shape}", key, "birth_step")
        if birth.size and (birth.min() < 0 or birth.max() >= pos.shape[0]):
            raise DatasetError(path, f"expected frames in [0, {pos.shape[0]}), got [{birth.min()}, "
                               f"{birth.max()}]", key, "birth_step")


def _read_group(path: Path, key: str, group: Any) -> Trajectory:
    if not isinstance(group, h5py.Group):
        raise DatasetError(path, f"expected a group of arrays, found a {type(group).__name__}", key)
    fields = set(group.keys())
    missing = [f for f in REQUIRED_FIELDS if f not in fields]
    if missing:
        raise DatasetError(path, f"missing key(s) {missing}; a trajectory holds {list(REQUIRED_FIELDS)} "
                           f"and optionally {list(OPTIONAL_FIELDS)}", key, missing[0])
    extra = sorted(fields - set(REQUIRED_FIELDS) - set(OPTIONAL_FIELDS))
    if extra:
        raise DatasetError(path, f"unexpected key(s) {extra}; a trajectory holds {list(REQUIRED_FIELDS)} "
                           f"and optionally {list(OPTIONAL_FIELDS)}", key, extra[0])
    arrays = {}
    for name in fields:
        try:
            arrays[name] = group[name][()]
        except Exception as exc:  # h5py raises OSError, KeyError or RuntimeError on corrupt chunks
            raise DatasetError(path, f"unreadable ({exc})", key, name) from exc
    def typed(name: str, kind: type, dtype: type) -> np.ndarray | None:
        """The field as `dtype`, if present; a DatasetError when it is not of `kind` (floating/integer)."""
        if name not in arrays:
            return None
        array = np.asarray(arrays[name])
        if not np.issubdtype(array.dtype, kind):
            raise DatasetError(path, f"expected {np.dtype(dtype).name}, got {array.dtype}", key, name)
        return array.astype(dtype)

    pos, types = typed("position", np.floating, np.float32), typed("particle_type", np.integer, np.int64)
    ctx, birth = typed("step_context", np.floating, np.float32), typed("birth_step", np.integer, np.int64)
    return Trajectory(pos, types, ctx, birth)


def _validated(dataset_dir: str | os.PathLike, split: str, meta: Metadata | None, min_length: int,
               bounds_tolerance: float) -> Iterator[Trajectory]:
    """Each trajectory of one split, validated, one in memory at a time; `DatasetError` for the first problem."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    meta = meta or read_metadata(dataset_dir)
    path = Path(dataset_dir) / f"{split}.h5"
    if not path.is_file():
        raise DatasetError(path, "no such file")
    try:
        with h5py.File(path, "r") as f:
            keys = list(f.keys())
            if not keys:
                raise DatasetError(path, "no trajectories")
            for key in keys:
                if not (key.isdigit() and len(key) == 5):
                    raise DatasetError(path, "unexpected top-level key; trajectories are groups named "
                                       "00000, 00001, ...", key)
                traj = _read_group(path, key, f[key])
                validate_trajectory(traj, meta, path, key, min_length=min_length,
                                    bounds_tolerance=bounds_tolerance)
                yield traj
    except DatasetError:
        raise
    except Exception as exc:  # truncated or not an HDF5 file at all
        raise DatasetError(path, f"unreadable or truncated HDF5 file ({exc})") from exc


def load_split(dataset_dir: str | os.PathLike, split: str, meta: Metadata | None = None, *,
               min_length: int = 7, bounds_tolerance: float = DEFAULT_BOUNDS_TOLERANCE) -> list[Trajectory]:
    """Load and validate every trajectory of one split. Returns nothing unless all are valid."""
    return list(_validated(dataset_dir, split, meta, min_length, bounds_tolerance))


def check_split(dataset_dir: str | os.PathLike, split: str, meta: Metadata | None = None, *,
                min_length: int = 7, bounds_tolerance: float = DEFAULT_BOUNDS_TOLERANCE) -> int:
    """Validate one split as `load_split` does, one trajectory in memory at a time (seconds for a large split, no
    copy of it kept); returns its trajectory count. Raises `DatasetError` for the first problem."""
    return sum(1 for _ in _validated(dataset_dir, split, meta, min_length, bounds_tolerance))


def iter_split(dataset_dir: str | os.PathLike, split: str) -> Iterator[Trajectory]:
    """Stream a split's trajectories without validation (for statistics and hashing of our own writes)."""
    with h5py.File(Path(dataset_dir) / f"{split}.h5", "r") as f:
        for key in sorted(f.keys()):
            yield _read_group(Path(dataset_dir) / f"{split}.h5", key, f[key])


def content_hashes(dataset_dir: str | os.PathLike) -> tuple[str, dict[str, str]]:
    """SHA-256 of the arrays of every split in order (independent of HDF5 layout and file timestamps), and of
    each split alone, in one pass over the files."""
    whole = hashlib.sha256()
    splits = {}
    for split in SPLITS:
        if not (Path(dataset_dir) / f"{split}.h5").exists():
            continue
        part = hashlib.sha256()
        for digest in (whole, part):
            digest.update(split.encode())
        for traj in iter_split(dataset_dir, split):
            for array in (traj.position, traj.particle_type, traj.step_context, traj.birth_step):
                if array is not None:
                    for digest in (whole, part):
                        digest.update(str(array.shape).encode())
                        digest.update(np.ascontiguousarray(array).tobytes())
        splits[split] = part.hexdigest()
    return whole.hexdigest(), splits


def content_hash(dataset_dir: str | os.PathLike) -> str:
    """`metadata.json`'s `content_hash`: SHA-256 of the arrays of every split (`content_hashes`)."""
    return content_hashes(dataset_dir)[0]


# ----------------------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------------------

_COMPLETE_ATTR = "complete"


def write_trajectory(f: h5py.File, key: str, traj: Trajectory) -> None:
    group = f.create_group(key, track_order=True)
    group.create_dataset("position", data=traj.position.astype(np.float32), track_times=False)
    group.create_dataset("particle_type", data=traj.particle_type.astype(np.int64), track_times=False)
    if traj.step_context is not None:
        group.create_dataset("step_context", data=traj.step_context.astype(np.float32), track_times=False)
    if traj.birth_step is not None:
        group.create_dataset("birth_step", data=traj.birth_step.astype(np.int64), track_times=False)
    group.attrs[_COMPLETE_ATTR] = 1  # written last: a group without it was cut off mid-write
    f.flush()


class DatasetWriter:
    """Writes a dataset under `<out>.partial/` and renames it to `<out>/` only once complete.

    Re-opening the same partial directory resumes it: complete trajectories are kept (`count(split)`
    tells how many) and a trajectory cut off mid-write is dropped.
    """

    def __init__(self, out_dir: str | os.PathLike, *, overwrite: bool = False):
        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not overwrite:
            raise FileExistsError(f"{self.out_dir} already exists (pass overwrite=True to replace it)")
        self.partial_dir = self.out_dir.with_name(self.out_dir.name + ".partial")
        self.partial_dir.mkdir(parents=True, exist_ok=True)
        self._counts = {split: self._repair(split) for split in SPLITS}

    def _repair(self, split: str) -> int:
        path = self.partial_dir / f"{split}.h5"
        if not path.exists():
            return 0
        try:
            with h5py.File(path, "a") as f:
                keys = sorted(f.keys())
                complete = 0
                for key in keys:
                    if f[key].attrs.get(_COMPLETE_ATTR, 0) == 1 and key == f"{complete:05d}":
                        complete += 1
                    else:
                        break
                for key in keys[complete:]:
                    del f[key]
                return complete
        except OSError as exc:  # the file itself was cut off: start the split again
            print(f"{path}: unreadable ({exc}), left by an interrupted write; generating this split again",
                  file=sys.stderr)
            path.unlink()
            return 0

    def count(self, split: str) -> int:
        return self._counts[split]

    def add(self, split: str, traj: Trajectory) -> None:
        with h5py.File(self.partial_dir / f"{split}.h5", "a") as f:
            write_trajectory(f, f"{self._counts[split]:05d}", traj)
        self._counts[split] += 1

    def finish(self, meta: Metadata) -> Path:
        """Validate everything written, add the content hash, write metadata and rename into place."""
        if not any(self._counts.values()):
            raise DatasetError(self.partial_dir, "no trajectories in any split; nothing to finish")
        for split in SPLITS:
            if self._counts[split]:  # an evaluation-only dataset (a stress scene) may hold only `test`
                load_split(self.partial_dir, split, meta)  # raises on anything wrong; nothing is renamed
        meta.content_hash, meta.extra["split_hashes"] = content_hashes(self.partial_dir)
        write_json_atomic(self.partial_dir / "metadata.json", meta.to_json())
        if self.out_dir.exists():
            import shutil

            shutil.rmtree(self.out_dir)
        os.replace(self.partial_dir, self.out_dir)
        return self.out_dir


def write_dataset(out_dir: str | os.PathLike, meta: Metadata, splits: dict[str, Iterable[Trajectory]], *,
                  overwrite: bool = False) -> Path:
    """Write a whole dataset at once (importers, tests). `meta` statistics must already be filled in."""
    writer = DatasetWriter(out_dir, overwrite=overwrite)
    for split in SPLITS:
        if writer.count(split):
            raise FileExistsError(f"{writer.partial_dir} holds an earlier partial write; remove it first")
        for traj in splits.get(split, ()):
            writer.add(split, traj)
    return writer.finish(meta)
