"""The dataset format: round trip, atomic writes with resume, and one clear error per bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from gns_bench.data.format import (
    DatasetError,
    DatasetWriter,
    Metadata,
    Trajectory,
    content_hash,
    load_split,
    read_metadata,
    write_dataset,
)
from gns_bench.data.statistics import compute_statistics


def make_traj(rng: np.random.Generator, t: int = 10, n: int = 5, d: int = 2, context: bool = False) -> Trajectory:
    pos = rng.uniform(0.2, 0.8, size=(t, n, d)).astype(np.float32)
    types = np.array([5] * (n - 1) + [3], dtype=np.int64)
    ctx = rng.normal(size=(t, 1)).astype(np.float32) if context else None
    return Trajectory(pos, types, ctx)


def make_meta(d: int = 2, **kw) -> Metadata:
    base = dict(bounds=[[0.0, 1.0]] * d, sequence_length=9, default_connectivity_radius=0.1, dim=d, dt=0.01,
                vel_mean=[0.0] * d, vel_std=[1.0] * d, acc_mean=[0.0] * d, acc_std=[1.0] * d,
                name="test", particle_types={"water": 5, "kinematic": 3})
    base.update(kw)
    return Metadata(**base)


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    splits = {s: [make_traj(rng) for _ in range(2)] for s in ("train", "valid", "test")}
    return write_dataset(tmp_path / "ds", make_meta(), splits)


def test_round_trip_and_hash(dataset: Path) -> None:
    meta = read_metadata(dataset)
    assert meta.content_hash and len(meta.content_hash) == 64
    assert content_hash(dataset) == meta.content_hash
    trajs = load_split(dataset, "train", meta)
    assert len(trajs) == 2 and trajs[0].position.dtype == np.float32 and trajs[0].position.shape == (10, 5, 2)
    assert trajs[0].particle_type.dtype == np.int64
    assert not (dataset.parent / "ds.partial").exists()


def test_metadata_keeps_unknown_keys_and_paper_fields(tmp_path: Path) -> None:
    meta = make_meta()
    data = meta.to_json() | {"case": "TGV", "periodic_boundary_conditions": [False, False]}
    again = Metadata.from_json(data)
    assert again.extra == {"case": "TGV", "periodic_boundary_conditions": [False, False]}
    for key in ("bounds", "sequence_length", "default_connectivity_radius", "dim", "dt", "vel_mean", "vel_std",
                "acc_mean", "acc_std"):
        assert key in again.to_json()


def test_statistics_match_finite_differences() -> None:
    rng = np.random.default_rng(1)
    traj = make_traj(rng, t=30, n=20)
    stats = compute_statistics([traj])
    moving = traj.position[:, traj.particle_type != 3].astype(np.float64)
    vel = np.diff(moving, axis=0)
    acc = np.diff(vel, axis=0)
    np.testing.assert_allclose(stats["vel_mean"], vel.reshape(-1, 2).mean(0), rtol=1e-10)
    np.testing.assert_allclose(stats["vel_std"], vel.reshape(-1, 2).std(0), rtol=1e-8)
    np.testing.assert_allclose(stats["acc_std"], acc.reshape(-1, 2).std(0), rtol=1e-8)


def test_writer_resumes_and_drops_a_torn_trajectory(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    trajs = [make_traj(rng) for _ in range(3)]
    writer = DatasetWriter(tmp_path / "ds")
    writer.add("train", trajs[0])
    writer.add("train", trajs[1])
    with h5py.File(writer.partial_dir / "train.h5", "a") as f:  # a write cut off before its marker
        f.create_group("00002").create_dataset("position", data=trajs[2].position)
    resumed = DatasetWriter(tmp_path / "ds")
    assert resumed.count("train") == 2
    assert not (tmp_path / "ds").exists(), "an unfinished dataset must not look complete"
    resumed.add("train", trajs[2])
    for split in ("valid", "test"):
        resumed.add(split, trajs[0])
    out = resumed.finish(make_meta())
    loaded = load_split(out, "train")
    np.testing.assert_array_equal(loaded[2].position, trajs[2].position)


def test_writer_says_when_it_discards_a_damaged_partial_file(tmp_path: Path, capsys) -> None:
    rng = np.random.default_rng(3)
    writer = DatasetWriter(tmp_path / "ds")
    writer.add("train", make_traj(rng))
    path = writer.partial_dir / "train.h5"
    path.write_bytes(path.read_bytes()[:100])  # the file itself cut off by a killed generation
    assert DatasetWriter(tmp_path / "ds").count("train") == 0
    err = capsys.readouterr().err
    assert "train.h5" in err and "generating this split again" in err


def test_unfinished_dataset_is_not_loadable(tmp_path: Path) -> None:
    writer = DatasetWriter(tmp_path / "ds")
    writer.add("train", make_traj(np.random.default_rng(0)))
    with pytest.raises(DatasetError, match="metadata.json"):
        read_metadata(tmp_path / "ds")


# --- bad input: every case names the file, the trajectory and the field ---------------------------------

def _rewrite(dataset: Path, mutate) -> None:
    with h5py.File(dataset / "train.h5", "a") as f:
        mutate(f["00001"])


def _replace(group: h5py.Group, name: str, data: np.ndarray) -> None:
    del group[name]
    group.create_dataset(name, data=data)


@pytest.mark.parametrize(
    "mutate, field, message",
    [
        (lambda g: g.__delitem__("particle_type"), "particle_type", "missing key"),
        (lambda g: g.create_dataset("velocity", data=np.zeros(3)), "velocity", "unexpected key"),
        (lambda g: _replace(g, "position", np.zeros((10, 5), np.float32)), "position", "rank 3"),
        (lambda g: _replace(g, "position", np.full((10, 5, 3), 0.5, np.float32)), "position", "dim D=2"),
        (lambda g: _replace(g, "position", np.full((4, 5, 2), 0.5, np.float32)), "position", "shorter than"),
        (lambda g: _replace(g, "position", np.where(np.arange(100).reshape(10, 5, 2) == 37, np.nan, 0.5)
                            .astype(np.float32)), "position", "NaN or inf"),
        (lambda g: _replace(g, "particle_type", np.array([5, 5, 5, 5, 7])), "particle_type", "not among"),
        (lambda g: _replace(g, "particle_type", np.array([5, 5, 5])), "particle_type", "shape"),
        (lambda g: _replace(g, "position", np.full((10, 5, 2), 1.5, np.float32)), "position", "outside"),
        (lambda g: _replace(g, "position", np.zeros((10, 5, 2), np.int32)), "position", "float32"),
        (lambda g: g.create_dataset("step_context", data=np.zeros((3, 1), np.float32)), "step_context",
         "shape"),
    ],
)
def test_bad_trajectory_names_file_trajectory_and_field(dataset: Path, mutate, field: str, message: str) -> None:
    _rewrite(dataset, mutate)
    with pytest.raises(DatasetError, match=message) as info:
        load_split(dataset, "train")
    error = info.value
    assert error.path.endswith("train.h5") and error.trajectory == "00001" and error.field == field
    assert "train.h5, trajectory 00001, field" in str(error)


def test_truncated_file(dataset: Path) -> None:
    data = (dataset / "train.h5").read_bytes()
    (dataset / "train.h5").write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="unreadable or truncated") as info:
        load_split(dataset, "train")
    assert info.value.path.endswith("train.h5")


def test_not_an_hdf5_file(dataset: Path) -> None:
    (dataset / "test.h5").write_text("hello")
    with pytest.raises(DatasetError, match="test.h5: unreadable"):
        load_split(dataset, "test")


def test_missing_context_when_declared(dataset: Path) -> None:
    meta = json.loads((dataset / "metadata.json").read_text())
    meta |= {"context_mean": [0.0], "context_std": [1.0]}
    (dataset / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="step_context"):
        load_split(dataset, "train")


@pytest.mark.parametrize(
    "change, key",
    [({"dim": 4}, "dim"), ({"bounds": [[0, 1]]}, "bounds"), ({"vel_std": [1.0]}, "vel_std"),
     ({"particle_types": {"water": 12}}, "particle_types"), ({"context_mean": [0.0]}, "context_std")],
)
def test_bad_metadata(dataset: Path, change: dict, key: str) -> None:
    meta = json.loads((dataset / "metadata.json").read_text()) | change
    (dataset / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=f"metadata.json, field '{key}'"):
        read_metadata(dataset)


def test_missing_metadata_key(dataset: Path) -> None:
    meta = json.loads((dataset / "metadata.json").read_text())
    del meta["acc_std"]
    (dataset / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="missing key 'acc_std'"):
        read_metadata(dataset)


def test_nothing_is_half_loaded(dataset: Path) -> None:
    """A bad last trajectory fails the whole split: no partial list comes back."""
    _rewrite(dataset, lambda g: _replace(g, "particle_type", np.array([5, 5, 5, 5, 8])))
    result = None
    with pytest.raises(DatasetError):
        result = load_split(dataset, "train")
    assert result is None


def test_write_refuses_to_clobber(dataset: Path) -> None:
    with pytest.raises(FileExistsError):
        write_dataset(dataset, make_meta(), {})
    shutil.rmtree(dataset)
