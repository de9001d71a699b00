"""The generation pipeline: every domain at smoke tier, reproducibility, resume, failures never written."""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

import gns_bench.physics.generate as generate_module
import gns_bench.physics.mpm as mpm
from gns_bench.data.format import (
    KINEMATIC_PARTICLE_TYPE,
    SPLITS,
    DatasetWriter,
    content_hash,
    load_split,
    read_metadata,
)
from gns_bench.datasets import ensure_dataset
from gns_bench.physics.generate import GENERATOR_VERSION, GenerationError, generate_dataset, time_generation
from gns_bench.physics.spec import list_domains, load_domain_spec


@pytest.mark.parametrize("domain", list_domains())
def test_domain_generates_at_smoke_tier_and_loads(domain: str, smoke_dataset: Callable[[str], Path]) -> None:
    spec = load_domain_spec(domain)
    path = smoke_dataset(domain)
    meta = read_metadata(path)
    tier = spec.tier("smoke")
    assert meta.sequence_length == tier.sequence_length and meta.dim == spec.dim
    assert meta.particle_types == spec.particle_types and meta.walls == spec.walls
    assert meta.generator == {"name": "gns-bench", "version": meta.generator["version"],
                              "generator_version": GENERATOR_VERSION, "domain": domain, "tier": "smoke",
                              "seed": 0, "solver": spec.solver}
    assert not (path / generate_module.VERSION_FILE).exists()  # the partial's marker, now in the metadata
    assert np.allclose(meta.gravity, np.asarray(spec.gravity) * spec.dt**2)
    assert (meta.context_mean is not None) == (spec.context is not None)
    bounds = np.asarray(spec.bounds)
    for split in SPLITS:
        trajectories = load_split(path, split, meta)
        assert len(trajectories) == tier.trajectories[split]
        for traj in trajectories:
            assert traj.position.shape[0] == tier.sequence_length + 1
            # particle count and types are fixed per trajectory by construction of the format; the
            # solver must also keep every particle inside the container, not merely within tolerance
            assert np.all(traj.position >= bounds[:, 0] - 1e-5)
            assert np.all(traj.position <= bounds[:, 1] + 1e-5)
            moving = traj.particle_type != KINEMATIC_PARTICLE_TYPE
            assert moving.any()
            step = np.linalg.norm(np.diff(traj.position[:, moving], axis=0), axis=-1)
            # the paper's scale: particles move a small fraction of the connectivity radius per frame
            assert np.percentile(step, 99) < 0.5 * spec.connectivity_radius
            assert step.max() > 0.0


@pytest.mark.parametrize("domain", ["waterramps", "fluidshake"])
def test_kinematic_particles_follow_the_scene(domain: str, smoke_dataset: Callable[[str], Path]) -> None:
    for traj in load_split(smoke_dataset(domain), "train"):
        kinematic = traj.position[:, traj.particle_type == KINEMATIC_PARTICLE_TYPE]
        assert kinematic.shape[1] > 10
        motion = np.abs(kinematic - kinematic[0]).max()
        if domain == "waterramps":
            assert motion == 0.0  # static ramps
        else:
            assert motion > 1e-4  # the shaken container moves horizontally only
            assert np.all(kinematic[:, :, 1] == kinematic[0, :, 1])


def test_continuous_stores_friction_angle_as_step_context(smoke_dataset: Callable[[str], Path]) -> None:
    path = smoke_dataset("continuous")
    for split in SPLITS:
        for traj in load_split(path, split):
            ctx = traj.step_context
            assert ctx is not None and ctx.shape == (traj.num_steps, 1)
            assert np.all(ctx == ctx[0]) and 0.0 <= ctx[0, 0] <= 80.0
            if split != "test":
                assert not 30.0 < ctx[0, 0] < 55.0


def test_same_seed_same_files_other_seed_other_files(tmp_path: Path,
                                                     smoke_dataset: Callable[[str], Path]) -> None:
    again = generate_dataset("waterdrop", "smoke", seed=0, out=tmp_path / "again", progress=False)
    other = generate_dataset("waterdrop", "smoke", seed=1, out=tmp_path / "other", progress=False)
    first = smoke_dataset("waterdrop")
    assert content_hash(again) == content_hash(first)
    assert content_hash(other) != content_hash(first)
    metadata = [json.loads((p / "metadata.json").read_text()) for p in (again, first)]
    assert metadata[0] == metadata[1]
    # a complete dataset is returned unchanged
    stamp = (again / "train.h5").stat().st_mtime_ns
    assert generate_dataset("waterdrop", "smoke", seed=0, out=again, progress=False) == again
    assert (again / "train.h5").stat().st_mtime_ns == stamp


def test_timing_a_tier_simulates_its_first_trajectories_and_writes_nothing(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    tier = load_domain_spec("waterdrop").tier("smoke")
    timing = time_generation("waterdrop", "smoke", budget_seconds=0.0)
    assert timing.timed == min(3, tier.trajectories["train"]) and timing.trajectories == sum(tier.trajectories.values())
    assert timing.first_seconds > 0 and timing.seconds_per_trajectory > 0 and timing.mean_particles > 0
    expected = (timing.first_seconds + (timing.trajectories - 1) * timing.seconds_per_trajectory) / 60
    assert timing.estimated_minutes == pytest.approx(expected)
    assert list(tmp_path.iterdir()) == []  # nothing written


_THREADED_RUN = """
import hashlib, numpy as np
from gns_bench.physics.mpm import MaterialParams, run_scene
from gns_bench.physics.mpm_kernels import WATER
from gns_bench.physics.scenes import block_scene
b = [[0.1, 0.9], [0.1, 0.9]]
scene = block_scene(WATER, 5, [0.1, 0.1], [0.5, 0.6], b, 128, np.random.default_rng(0))
# shuffled particles: every thread's chunk of the P2G loop then scatters onto every grid region
order = np.random.default_rng(0).permutation(len(scene.position))
scene.position, scene.velocity = scene.position[order], scene.velocity[order]
pos = run_scene(scene, MaterialParams(), grid=128, gravity=[0, -9.81], frame_dt=0.0025, frames=8, bounds=b)
print(len(order), hashlib.sha256(pos.tobytes()).hexdigest())
"""


def test_particle_to_grid_scatter_is_deterministic_across_thread_counts(digests_across_threads) -> None:
    """Float atomic adds would make the result depend on scheduling; the fixed-point scatter must not."""
    assert len(digests_across_threads(_THREADED_RUN, ("1", "4"))) == 1


def test_resume_after_interruption_gives_identical_dataset(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                           smoke_dataset: Callable[[str], Path]) -> None:
    real = mpm.simulate
    calls = {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt("simulated interruption")
        return real(*args, **kwargs)

    out = tmp_path / "resumed"
    monkeypatch.setattr(mpm, "simulate", interrupted)
    with pytest.raises(KeyboardInterrupt):
        generate_dataset("sand", "smoke", seed=0, out=out, progress=False)
    assert not out.exists() and (tmp_path / "resumed.partial").is_dir()
    monkeypatch.setattr(mpm, "simulate", real)
    resumed = generate_dataset("sand", "smoke", seed=0, out=out, progress=False)
    assert content_hash(resumed) == content_hash(smoke_dataset("sand"))
    assert not (tmp_path / "resumed.partial").exists()


def test_exploding_trajectory_is_reported_and_never_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    spec = load_domain_spec("waterdrop")
    exploding = dataclasses.replace(spec, scene={**spec.scene, "initial_speed": 500.0})
    monkeypatch.setattr(generate_module, "load_domain_spec", lambda domain: exploding)
    out = tmp_path / "boom"
    expected = r"waterdrop tier smoke seed 0, train trajectory 0: 3 attempts failed: attempt 0: SimulationError"
    with pytest.raises(GenerationError, match=expected):
        generate_dataset("waterdrop", "smoke", seed=0, out=out, progress=False)
    assert capsys.readouterr().err.count("simulation failed, not written") == 3
    assert not out.exists()
    partial = tmp_path / "boom.partial"
    assert not (partial / "train.h5").exists() and not (partial / "metadata.json").exists()


def test_a_failed_draw_is_redrawn_deterministically(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real = mpm.simulate
    doomed = generate_module.trajectory_rng("sand", 0, "train", 1).bit_generator.state

    def blows_up_on_one_draw(spec, tier_name, rng):
        if rng.bit_generator.state == doomed:  # train trajectory 1, first attempt
            raise mpm.SimulationError("injected blow-up")
        return real(spec, tier_name, rng)

    monkeypatch.setattr(mpm, "simulate", blows_up_on_one_draw)
    runs = [generate_dataset("sand", "smoke", seed=0, out=tmp_path / f"run{k}", progress=False) for k in (0, 1)]
    assert content_hash(runs[0]) == content_hash(runs[1])
    train = load_split(runs[0], "train")
    spec = load_domain_spec("sand").for_split("train")
    redraw = real(spec, "smoke", generate_module.trajectory_rng("sand", 0, "train", 1, attempt=1))
    first_draw = real(spec, "smoke", generate_module.trajectory_rng("sand", 0, "train", 1))
    assert np.array_equal(train[1].position, redraw.position)
    assert train[1].position.shape != first_draw.position.shape or \
        not np.array_equal(train[1].position, first_draw.position)


def _set_generator(path: Path, **changes: object) -> None:
    """Rewrite a dataset's metadata generator (a key set to None is removed): an older or foreign dataset."""
    meta_path = path / "metadata.json"
    meta = json.loads(meta_path.read_text())
    meta["generator"].update(changes)
    meta["generator"] = {k: v for k, v in meta["generator"].items() if v is not None}
    meta_path.write_text(json.dumps(meta))


def test_stale_dataset_is_moved_aside_and_generated_afresh(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                           smoke_dataset: Callable[[str], Path]) -> None:
    """An MPM dataset from before GENERATOR_VERSION 2 (no generator_version: 1, lattice seeding) is not
    reused: it is moved aside, never deleted, even past an earlier stale copy, and generated afresh."""
    out = tmp_path / "waterdrop-smoke-s0"
    shutil.copytree(smoke_dataset("waterdrop"), out)
    _set_generator(out, generator_version=None)
    old_meta = (out / "metadata.json").read_text()
    earlier = tmp_path / "waterdrop-smoke-s0.stale-v1"
    earlier.mkdir()
    (earlier / "note").write_text("an earlier stale copy")
    capsys.readouterr()
    assert ensure_dataset("waterdrop", "smoke", 0, out=out, progress=False) == out
    assert "stale, moved aside to" in capsys.readouterr().err
    aside = tmp_path / "waterdrop-smoke-s0.stale-v1-2"
    assert (aside / "metadata.json").read_text() == old_meta and (aside / "train.h5").is_file()
    assert (earlier / "note").read_text() == "an earlier stale copy"
    assert read_metadata(out).generator["generator_version"] == GENERATOR_VERSION
    assert content_hash(out) == content_hash(smoke_dataset("waterdrop"))
    stamp = (out / "train.h5").stat().st_mtime_ns  # now current: reused as it is
    assert ensure_dataset("waterdrop", "smoke", 0, out=out, progress=False) == out
    assert (out / "train.h5").stat().st_mtime_ns == stamp
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, earlier.name, aside.name])


def test_stale_partial_dataset_is_not_resumed(tmp_path: Path, smoke_dataset: Callable[[str], Path]) -> None:
    """An interrupted generation of an older version (no version marker) is moved aside, not completed with
    trajectories of another seeding."""
    out = tmp_path / "sand"
    old = load_split(smoke_dataset("sand"), "train")[0]
    writer = DatasetWriter(out)
    writer.add("train", dataclasses.replace(old, position=old.position + np.float32(1e-3)))
    assert not (writer.partial_dir / generate_module.VERSION_FILE).exists()
    generate_dataset("sand", "smoke", seed=0, out=out, progress=False)
    assert content_hash(out) == content_hash(smoke_dataset("sand"))
    assert (tmp_path / "sand.partial.stale-v1" / "train.h5").is_file()


def test_current_sph_pbd_imported_and_tiny_datasets_are_reused(tmp_path: Path,
                                                             smoke_dataset: Callable[[str], Path]) -> None:
    """Only data whose solver has changed since its version is stale: version-1 SPH and PBD data (their
    lattices are kept) and datasets this generator did not make (imported, tiny) are reused untouched."""
    cases = {"water-3d-s": {"solver": "sph", "generator_version": None},
             "boxbath": {"solver": "pbd", "generator_version": None},
             "waterramps": {"name": "gns-bench import", "generator_version": None},
             "tiny": {"solver": "analytic", "domain": "tiny", "generator_version": None}}
    for domain, changes in cases.items():
        out = tmp_path / domain
        shutil.copytree(smoke_dataset("waterdrop"), out)  # any small dataset: only its metadata is read
        _set_generator(out, **changes)
        assert generate_module.stale_generator_version(out) is None
        assert ensure_dataset(domain, "smoke", 0, out=out, progress=False) == out
        assert content_hash(out) == content_hash(smoke_dataset("waterdrop"))
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(cases)


def test_statistics_come_from_the_generated_train_split(smoke_dataset: Callable[[str], Path]) -> None:
    path = smoke_dataset("waterdrop")
    meta = read_metadata(path)
    train = load_split(path, "train")
    velocities = np.concatenate([np.diff(t.position, axis=0).reshape(-1, 2) for t in train])
    assert np.allclose(meta.vel_mean, velocities.mean(axis=0), rtol=1e-4, atol=1e-9)
    assert np.allclose(meta.vel_std, velocities.std(axis=0), rtol=1e-4)
    accelerations = np.concatenate([np.diff(t.position, n=2, axis=0).reshape(-1, 2)
                                    for t in train])
    assert np.allclose(meta.acc_std, accelerations.std(axis=0), rtol=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("domain", [d for d in list_domains() if load_domain_spec(d).solver == "mpm"])
def test_small_tier_trajectory_runs_its_full_length(domain: str) -> None:
    """Minutes per domain: a full-length small-tier trajectory must neither blow up nor stall."""
    spec = load_domain_spec(domain)
    traj = mpm.simulate(spec.for_split("train"), "small", generate_module.trajectory_rng(domain, 0, "train", 0))
    generate_module.check_trajectory(traj, spec, spec.tier("small").sequence_length, domain)
    moving = traj.particle_type != KINEMATIC_PARTICLE_TYPE
    step = np.linalg.norm(np.diff(traj.position[:, moving], axis=0), axis=-1)
    assert np.percentile(step, 99) < spec.connectivity_radius
    assert step[:50].mean() > 1e-4  # the material does move at first
