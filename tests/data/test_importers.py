"""Importers, on small files written here in the DeepMind TFRecord and geoelements npz layouts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from tfrecord.writer import TFRecordWriter

from gns_bench.cli import main
from gns_bench.data.format import DatasetError, load_split, read_metadata

DEEPMIND_META = {  # WaterDropSample's metadata.json fields (DeepMind's release), with its statistics
    "bounds": [[0.1, 0.9], [0.1, 0.9]], "sequence_length": 9, "default_connectivity_radius": 0.015, "dim": 2,
    "dt": 0.0025, "vel_mean": [-4.0e-5, -2.6e-4], "vel_std": [1.37e-3, 1.31e-3], "acc_mean": [2.6e-8, 1.1e-7],
    "acc_std": [6.7e-5, 8.7e-5],
}


def trajectories(seed: int, count: int, context: bool = False) -> list[tuple]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        n = int(rng.integers(5, 9))
        pos = rng.uniform(0.2, 0.8, size=(10, n, 2)).astype(np.float32)
        types = np.where(np.arange(n) < n - 2, 5, 3).astype(np.int64)
        ctx = rng.normal(size=(10, 1)).astype(np.float32) if context else None
        out.append((pos, types, ctx))
    return out


def write_deepmind(src: Path, context: bool = False) -> dict[str, list[tuple]]:
    src.mkdir(parents=True)
    meta = dict(DEEPMIND_META)
    if context:
        meta |= {"context_mean": [0.0], "context_std": [1.0]}
    (src / "metadata.json").write_text(json.dumps(meta))
    written = {}
    for seed, split in enumerate(("train", "valid", "test")):
        trajs = trajectories(seed, 3 if split == "train" else 1, context)
        writer = TFRecordWriter(str(src / f"{split}.tfrecord"))
        for key, (pos, types, ctx) in enumerate(trajs):
            sequence = {"position": ([frame.tobytes() for frame in pos], "byte")}
            if ctx is not None:
                sequence["step_context"] = ([row.tobytes() for row in ctx], "byte")
            writer.write({"key": (key, "int"), "particle_type": (types.tobytes(), "byte")}, sequence)
        writer.close()
        written[split] = trajs
    return written


@pytest.mark.parametrize("context", [False, True])
def test_import_deepmind(tmp_path: Path, context: bool) -> None:
    written = write_deepmind(tmp_path / "src", context)
    assert main(["import", "deepmind", str(tmp_path / "src"), str(tmp_path / "dst")]) == 0
    meta = read_metadata(tmp_path / "dst")
    assert meta.default_connectivity_radius == 0.015 and meta.vel_std == DEEPMIND_META["vel_std"]
    assert meta.particle_types == {"type_3": 3, "type_5": 5}
    for split, trajs in written.items():
        loaded = load_split(tmp_path / "dst", split, meta)
        assert len(loaded) == len(trajs)
        for got, (pos, types, ctx) in zip(loaded, trajs, strict=True):
            np.testing.assert_array_equal(got.position, pos)
            np.testing.assert_array_equal(got.particle_type, types)
            if context:
                np.testing.assert_array_equal(got.step_context, ctx)
            else:
                assert got.step_context is None


def test_import_deepmind_truncated_file(tmp_path: Path) -> None:
    write_deepmind(tmp_path / "src")
    path = tmp_path / "src" / "valid.tfrecord"
    path.write_bytes(path.read_bytes()[:-40])
    with pytest.raises(DatasetError, match="valid.tfrecord: unreadable or truncated TFRecord"):
        from gns_bench.data.importers import import_deepmind

        import_deepmind(tmp_path / "src", tmp_path / "dst")
    assert not (tmp_path / "dst").exists()


def test_import_deepmind_wrong_dim(tmp_path: Path) -> None:
    write_deepmind(tmp_path / "src")
    meta = json.loads((tmp_path / "src" / "metadata.json").read_text())
    meta |= {"dim": 3, "bounds": [[0.1, 0.9]] * 3, **{k: meta[k] + [0.0] for k in
                                                      ("vel_mean", "vel_std", "acc_mean", "acc_std")}}
    (tmp_path / "src" / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="trajectory 00000, field 'position'.*D=3"):
        from gns_bench.data.importers import import_deepmind

        import_deepmind(tmp_path / "src", tmp_path / "dst")


def write_npz(src: Path, nested_meta: bool) -> dict[str, list[tuple]]:
    src.mkdir(parents=True)
    meta = {"train": DEEPMIND_META, "rollout": DEEPMIND_META} if nested_meta else DEEPMIND_META
    (src / "metadata.json").write_text(json.dumps(meta))
    written = {}
    for seed, split in enumerate(("train", "valid", "test")):
        trajs = trajectories(seed + 10, 2)
        entries = {}
        for i, (pos, types, _) in enumerate(trajs):
            item = np.empty(2, dtype=object)
            item[0], item[1] = pos, types
            entries[f"simulation_trajectory_{i}"] = item
        np.savez_compressed(src / f"{split}.npz", **entries)
        written[split] = trajs
    return written


@pytest.mark.parametrize("nested_meta", [False, True])
def test_import_npz(tmp_path: Path, nested_meta: bool) -> None:
    written = write_npz(tmp_path / "src", nested_meta)
    assert main(["import", "npz", str(tmp_path / "src"), str(tmp_path / "dst")]) == 0
    for split, trajs in written.items():
        loaded = load_split(tmp_path / "dst", split)
        for got, (pos, types, _) in zip(loaded, trajs, strict=True):
            np.testing.assert_array_equal(got.position, pos)
            np.testing.assert_array_equal(got.particle_type, types)


def test_import_npz_missing_split(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    write_npz(tmp_path / "src", False)
    (tmp_path / "src" / "test.npz").unlink()
    assert main(["import", "npz", str(tmp_path / "src"), str(tmp_path / "dst")]) == 2
    assert "test.npz: no such file" in capsys.readouterr().err
    assert not (tmp_path / "dst").exists()
