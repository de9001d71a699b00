"""Variants (datasets/variants/*.toml): specs resolved over their base domain, generated at smoke tier, and
the scene features they need: larger arenas, inflow, initial jitter, blob shapes, a context grid."""

from __future__ import annotations

import dataclasses
import functools
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import Delaunay, cKDTree

from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, SPLITS, load_split, read_metadata
from gns_bench.physics.geometry import (
    lattice_block,
    random_block,
    rectangle,
    solidity,
    union_sdf,
)
from gns_bench.physics.mpm import MaterialParams, material_params, run_scene
from gns_bench.physics.mpm_kernels import WATER
from gns_bench.physics.scenes import MpmScene, build_scene, inflow_emitters, scene_spec
from gns_bench.physics.spec import (
    SpecError,
    UnknownDomainError,
    list_domains,
    list_variants,
    load_domain_spec,
)

VARIANTS = ["boxbath-long", "boxbath-shake", "continuous-heldout", "goop-compact", "multimaterial-blob",
            "multimaterial-jitter",
            "waterramps-inflow", "waterramps-jitter", "waterramps-long", "waterramps-x2", "waterramps-x34",
            "waterramps-x8"]
TRAINABLE = {"boxbath-shake", "goop-compact"}  # the others are evaluation-only: test split alone
G, DT = 9.81, 0.0025


def test_variants_are_listed_apart_from_the_16_domains() -> None:
    assert len(list_domains()) == 16 and not set(list_domains()) & set(list_variants())
    assert list_variants() == VARIANTS
    for variant in VARIANTS:
        spec = load_domain_spec(variant)
        assert spec.id == variant and spec.base in list_domains() and spec.rng_domain == spec.base
        base = load_domain_spec(spec.base)
        assert spec.solver == base.solver and spec.dt == base.dt
        assert spec.particle_types.items() >= base.particle_types.items()  # a shaken box adds its walls
        for tier in spec.tiers.values():
            if variant in TRAINABLE:
                assert min(tier.trajectories.values()) > 0
            else:
                assert tier.trajectories["train"] == tier.trajectories["valid"] == 0 < tier.trajectories["test"]


# ----------------------------------------------------------------------------------------------
# Loading: deep merge and errors naming file and key
# ----------------------------------------------------------------------------------------------

def _specs_dir(tmp_path: Path, variant_text: str, name: str = "v") -> Path:
    (tmp_path / "variants").mkdir(exist_ok=True)
    for domain in ("waterdrop", "continuous"):
        (tmp_path / f"{domain}.toml").write_text(load_domain_spec(domain).path.read_text())
    (tmp_path / "variants" / f"{name}.toml").write_text(variant_text)
    return tmp_path


def test_variant_deep_merges_over_its_base(tmp_path: Path) -> None:
    specs = _specs_dir(tmp_path, 'base = "waterdrop"\nname = "V"\n[scene]\nblocks = [2, 2]\n'
                                 "[tiers.smoke]\ntrain = 0\nvalid = 0\nscene = { initial_jitter = 1e-4 }\n")
    spec, base = load_domain_spec("v", specs), load_domain_spec("waterdrop")
    assert (spec.id, spec.base, spec.name) == ("v", "waterdrop", "V")
    assert spec.scene == {**base.scene, "blocks": [2, 2]}  # tables merge key by key
    smoke = spec.tier("smoke")
    assert smoke.trajectories == {"train": 0, "valid": 0, "test": base.tier("smoke").trajectories["test"]}
    assert smoke.params["scene"] == {**base.tier("smoke").params["scene"], "initial_jitter": 1e-4}
    assert spec.tier("small") == base.tier("small")
    assert list_domains(specs) == ["continuous", "waterdrop"] and list_variants(specs) == ["v"]


@pytest.mark.parametrize("text, key", [
    ('base = "no-such-domain"\n', "base"),
    ('base = "waterdrop"\nid = "other"\n', "id"),
    ('base = "waterdrop"\n[tiers.smoke]\ntest = -1\n', "tiers.smoke.test"),
    ('base = "waterdrop"\n[tiers.smoke]\ntrain = 0\nvalid = 0\ntest = 0\n', "tiers.smoke.test"),
    ('base = "waterdrop"\n[tiers.small]\nbounds = [[0.1, 0.9]]\n', "tiers.small.bounds"),
    ('base = "continuous"\n[context]\nvalues = [0.0, 90.0]\n', "context.values"),
    # 40 degrees is held out of train, which the smoke tier fills
    ('base = "continuous"\n[context]\nvalues = [10.0, 40.0]\n', "context.values"),
])
def test_variant_errors_name_file_and_key(tmp_path: Path, text: str, key: str) -> None:
    specs = _specs_dir(tmp_path, text)
    with pytest.raises(SpecError) as info:
        load_domain_spec("v", specs)
    assert str(specs / "variants" / "v.toml") in str(info.value) and f"'{key}'" in str(info.value)


def test_unknown_id_lists_domains_and_variants() -> None:
    with pytest.raises(UnknownDomainError, match="waterramps-long"):
        load_domain_spec("waterramps-short")


# ----------------------------------------------------------------------------------------------
# Every variant at smoke tier, through the generator and the format's validation
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("variant", VARIANTS)
def test_variant_generates_at_smoke_tier_and_loads(variant: str, smoke_dataset: Callable[[str], Path]) -> None:
    spec = load_domain_spec(variant).for_tier("smoke")
    path = smoke_dataset(variant)
    meta = read_metadata(path)
    assert meta.generator["variant"] == variant and meta.generator["base"] == spec.base
    assert meta.generator["statistics_split"] == ("train" if variant in TRAINABLE else "test")
    assert meta.bounds == spec.bounds
    assert meta.name == spec.name and meta.sequence_length == spec.tier("smoke").sequence_length
    bounds = np.asarray(spec.bounds)
    for split in SPLITS:
        count = spec.tier("smoke").trajectories[split]
        if not count:
            assert not (path / f"{split}.h5").exists()
            continue
        trajectories = load_split(path, split, meta)
        assert len(trajectories) == count
        for traj in trajectories:
            assert np.all(traj.position >= bounds[:, 0] - 1e-5) and np.all(traj.position <= bounds[:, 1] + 1e-5)
            assert (traj.birth_step is not None) == (variant == "waterramps-inflow")


@pytest.mark.parametrize("variant, base", [("waterramps-long", "waterramps"), ("boxbath-long", "boxbath")])
def test_long_variant_starts_as_its_base_bit_for_bit(variant: str, base: str,
                                                     smoke_dataset: Callable[[str], Path]) -> None:
    long, short = load_split(smoke_dataset(variant), "test")[0], load_split(smoke_dataset(base), "test")[0]
    frames = short.num_steps
    assert long.num_steps == 8 * (frames - 1) + 1
    assert np.array_equal(long.position[:frames], short.position)
    assert np.array_equal(long.particle_type, short.particle_type)


# ----------------------------------------------------------------------------------------------
# Arenas larger than the unit square
# ----------------------------------------------------------------------------------------------

def _water_on_a_ramp(lo: list[float], hi: list[float], block_lo: list[float], block_hi: list[float],
                     ramp_centre: list[float], grid: int) -> MpmScene:
    pts = lattice_block(np.array(block_lo), np.array(block_hi), 0.5 / grid)
    ramp = rectangle(np.array(ramp_centre), 0.3, 0.04, 0.3)
    return MpmScene(pts, np.zeros_like(pts), np.full(len(pts), WATER), np.full(len(pts), 5), np.array(lo),
                    np.array(hi), [ramp])


def test_a_larger_grid_changes_nothing_inside_the_unit_square() -> None:
    """The grid now covers [0, ceil(upper bound)]: more nodes where no material goes must not change a bit."""
    grid, unit = 32, [[0.1, 0.9], [0.1, 0.9]]
    runs = []
    for bounds in (unit, [[0.1, 2.9], [0.1, 1.9]]):  # same container walls, grid 3 x 2 the unit square
        scene = _water_on_a_ramp([0.1, 0.1], [0.9, 0.9], [0.4, 0.5], [0.6, 0.7], [0.5, 0.35], grid)
        runs.append(run_scene(scene, MaterialParams(), grid=grid, gravity=[0.0, -G], frame_dt=DT, frames=30,
                              bounds=bounds))
    assert np.array_equal(runs[0], runs[1])


def test_water_in_an_8_by_4_arena_stays_in_and_lands_on_an_obstacle_far_from_the_origin() -> None:
    grid, bounds = 32, [[0.1, 7.9], [0.1, 3.9]]
    scene = _water_on_a_ramp([0.1, 0.1], [7.9, 3.9], [6.9, 0.75], [7.1, 0.9], [7.0, 0.6], grid)
    pts = lattice_block(np.array([7.6, 0.2]), np.array([7.8, 0.4]), 0.5 / grid)  # thrown at the right wall
    scene.position = np.concatenate([scene.position, pts])
    scene.velocity = np.concatenate([scene.velocity, np.tile([3.0, 0.0], (len(pts), 1))])
    scene.material = np.concatenate([scene.material, np.full(len(pts), WATER)])
    scene.particle_type = np.concatenate([scene.particle_type, np.full(len(pts), 5)])
    scene.birth_step = np.zeros(len(scene.position), np.int64)
    pos = run_scene(scene, MaterialParams(), grid=grid, gravity=[0.0, -G], frame_dt=DT, frames=100, bounds=bounds)
    assert pos[..., 0].max() <= 7.9 + 0.5 / grid and pos[..., 0].max() > 7.85  # it reached the wall
    on_ramp = pos[-1, : -len(pts)]
    depth = union_sdf(on_ramp.astype(float), scene.polygons)
    assert depth.min() > -0.5 / grid  # no water inside the ramp
    assert np.mean(np.abs(depth) < 0.1) > 0.5  # most of it is on the ramp (it fell 0.13 onto it)


@functools.cache
def _mean_particle_count(domain: str, tier: str, draws: int) -> float:
    spec = load_domain_spec(domain).for_tier(tier)
    models = material_params(spec)[1]
    counts = []
    for i in range(draws):
        scene = build_scene(spec, spec.tier(tier), models, np.random.default_rng(i))
        counts.append(len(scene.position) + (0 if scene.kinematic is None else len(scene.kinematic)))
    return float(np.mean(counts))


@pytest.mark.parametrize("variant, factor, draws", [("waterramps-x2", 2, 8), ("waterramps-x8", 8, 4),
                                                    ("waterramps-x34", 34, 2)])
def test_scaled_arenas_hold_the_scaled_particle_counts(variant: str, factor: int, draws: int) -> None:
    """Sec. 5.3's scale factors, against WATERRAMPS's small tier's mean count (1.13k: water and ramps)."""
    base = _mean_particle_count("waterramps", "small", 80)
    assert 0.8 * factor < _mean_particle_count(variant, "small", draws) / base < 1.25 * factor


# ----------------------------------------------------------------------------------------------
# Inflow
# ----------------------------------------------------------------------------------------------

def test_inflow_births_paths_and_free_fall(smoke_dataset: Callable[[str], Path]) -> None:
    spec = load_domain_spec("waterramps-inflow").for_tier("smoke")
    traj = load_split(smoke_dataset("waterramps-inflow"), "test")[0]
    pos, birth, frames = traj.position.astype(np.float64), traj.birth_step, traj.num_steps
    material = traj.particle_type != KINEMATIC_PARTICLE_TYPE
    assert np.all(birth[~material] == 0) and np.all(birth[material] >= 1) and birth.max() < frames
    active = np.array([np.sum(birth <= t) for t in range(frames)])
    assert np.all(np.diff(active) >= 0) and active[-1] > active[0] + 50
    velocities = np.array([e["velocity"] for e in spec.tier("smoke").params["scene"]["inflow"]]) * DT
    late = np.flatnonzero(birth >= 7)
    assert len(late) > 20
    for i in late:
        b = birth[i]
        assert np.all(pos[: b - 6, i] == pos[b - 6, i])  # still before its 6-frame history
        step = np.diff(pos[b - 6: b + 1, i], axis=0)  # the stream's velocity over [b - 6, b]
        assert min(np.abs(step - v).max() for v in velocities) < 1e-6
    # after birth the stream falls (no ramp within reach of the nozzles in 5 frames): at 0.7 g at this coarse
    # grid (0.85 g at the small tier's), as the weakly compressible water's tension between the accelerating
    # rows and the newborn ones behind them holds them back a little
    fresh = np.flatnonzero((birth >= 1) & (birth <= frames - 7))
    acc = np.array([np.diff(pos[birth[i]: birth[i] + 6, i, 1], n=2).mean() for i in fresh]) / DT**2
    assert -1.2 * G < acc.mean() < -0.55 * G


def test_inflow_particle_counts_match_the_stream_rate() -> None:
    """Rows s apart along the stream, round(width / s) particles each: rate = width |v| / s^2."""
    for tier, low, high in (("small", 1000, 5000), ("paper", 60000, 85000)):
        spec = load_domain_spec("waterramps-inflow").for_tier(tier)
        t = spec.tier(tier)
        spacing = 0.5 / t.params["grid"]
        scene = build_scene(spec, t, material_params(spec)[1], np.random.default_rng(0))
        expected = 0.0
        for e in t.params["scene"]["inflow"]:
            duration = (min(e["stop"], t.sequence_length) - e["start"]) * spec.dt
            expected += round(e["width"] / spacing) * np.linalg.norm(e["velocity"]) * duration / spacing
        assert abs(len(scene.position) - expected) <= 2 * 10 * len(t.params["scene"]["inflow"])
        assert low < len(scene.position) <= t.params["max_particles"] and len(scene.position) < high


def test_inflow_streams_are_seeded_at_random() -> None:
    """Each stream is i.i.d. uniform at one particle per spacing^2 (inflow.py), not rows on a lattice: taken
    back along its straight path to when it left the nozzle, a stream is a random sample of a strip of the
    nozzle's M cells' width, with the nearest-neighbour spread of random points; deterministic per rng."""
    spec = load_domain_spec("waterramps-inflow").for_tier("small")
    tier = spec.tier("small")
    spacing, bounds = 0.5 / tier.params["grid"], np.asarray(spec.bounds)
    emitter = inflow_emitters(spec, scene_spec(spec, tier), bounds[:, 0], bounds[:, 1], spacing)[0]
    pos, birth = emitter.particles(spacing, spec.dt, tier.sequence_length, np.random.default_rng(0))
    again, _ = emitter.particles(spacing, spec.dt, tier.sequence_length, np.random.default_rng(0))
    other, _ = emitter.particles(spacing, spec.dt, tier.sequence_length, np.random.default_rng(1))
    assert np.array_equal(pos, again) and not np.array_equal(pos, other)
    assert np.all(np.diff(birth) >= 0) and birth.min() >= emitter.start
    unit = emitter.velocity / emitter.speed
    rel = pos - emitter.position
    along = rel @ unit - emitter.speed * birth * spec.dt  # where it was when the stream's time was 0
    across = rel @ emitter.across
    half = 0.5 * emitter.row_count(spacing) * spacing
    assert np.all(np.abs(across) <= half) and np.ptp(across) > 0.95 * 2 * half
    assert np.all(rel @ unit >= -1e-9) and np.all(rel @ unit <= emitter.speed * spec.dt + 1e-9)  # born ahead
    strip = np.column_stack([along, across])
    # the stream's density: one particle per spacing^2 of strip
    assert len(strip) * spacing**2 == pytest.approx(np.ptp(along) * 2 * half, rel=0.01)
    nearest = cKDTree(strip).query(strip, k=2)[0][:, 1]
    assert nearest.std() / nearest.mean() > 0.4  # 0 on the former rows; ~0.5 for random points


@pytest.mark.parametrize("change, key", [
    ({"position": [0.5, 0.89]}, "inflow[0].position"),  # its 6-frame pre-birth path would leave the box
    ({"material": "sand"}, "inflow[0].material"),
    ({"velocity": [0.0, 0.0]}, "inflow[0].velocity"),
    ({"stop": 0}, "inflow[0].stop"),
])
def test_inflow_is_validated(change: dict, key: str) -> None:
    spec = load_domain_spec("waterramps-inflow")
    smoke = spec.tier("smoke")
    nozzle = {**smoke.params["scene"]["inflow"][0], **change}
    tier = dataclasses.replace(smoke, params={**smoke.params, "scene": {**smoke.params["scene"], "inflow": [nozzle]}})
    spec = dataclasses.replace(spec, tiers={**spec.tiers, "smoke": tier}).for_tier("smoke")
    with pytest.raises(ValueError, match=re.escape(f"'tiers.smoke.scene.{key}'")):
        build_scene(spec, tier, material_params(spec)[1], np.random.default_rng(0))


def test_inflow_beyond_max_particles_is_an_error() -> None:
    spec = load_domain_spec("waterramps-inflow").for_tier("smoke")
    smoke = spec.tier("smoke")
    tier = dataclasses.replace(smoke, params={**smoke.params, "max_particles": 50})
    with pytest.raises(ValueError, match="'tiers.smoke.max_particles'"):
        build_scene(spec, tier, material_params(spec)[1], np.random.default_rng(0))


# ----------------------------------------------------------------------------------------------
# Initial jitter, blobs, a context grid
# ----------------------------------------------------------------------------------------------

def test_initial_jitter_perturbs_only_the_initial_positions(smoke_dataset: Callable[[str], Path]) -> None:
    sigma = load_domain_spec("waterramps-jitter").scene["initial_jitter"]
    jittered = load_split(smoke_dataset("waterramps-jitter"), "test")[0]
    base = load_split(smoke_dataset("waterramps"), "test")[0]
    assert np.array_equal(jittered.particle_type, base.particle_type)  # the same scene
    kinematic = base.particle_type == KINEMATIC_PARTICLE_TYPE
    assert np.array_equal(jittered.position[:, kinematic], base.position[:, kinematic])
    offset = (jittered.position[0, ~kinematic] - base.position[0, ~kinematic]).astype(np.float64)
    rms = np.sqrt(np.mean(offset**2))  # per coordinate
    assert sigma / 2 < rms < 2 * sigma and abs(offset.mean()) < sigma / 3
    divergence = np.sqrt(np.mean((jittered.position[-1] - base.position[-1]).astype(np.float64) ** 2))
    assert np.isfinite(divergence) and divergence > 0.0


def _hull_voids(points: np.ndarray, spacing: float) -> float:
    """Fraction of the convex hull of randomly seeded particles farther than 1.5 spacings from every
    particle: the bays of a non-convex shape. About 0 for a convex one (a point inside it has no particle
    within 1.5 spacings with probability exp(-pi 1.5^2) ~ 1e-3, a little more along the hull's edges)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    grid = np.stack(np.meshgrid(*[np.arange(a, b, spacing / 4) for a, b in zip(lo, hi, strict=True)],
                                indexing="ij"), axis=-1).reshape(-1, 2)
    grid = grid[Delaunay(points).find_simplex(grid) >= 0]
    return float(np.mean(cKDTree(points).query(grid)[0] > 1.5 * spacing))


def test_blobs_are_non_convex_and_hold_both_materials(smoke_dataset: Callable[[str], Path]) -> None:
    spec = load_domain_spec("multimaterial-blob")
    for traj in load_split(smoke_dataset("multimaterial-blob"), "test"):
        assert set(np.unique(traj.particle_type)) == {spec.particle_types["water"], spec.particle_types["goop"]}
    # The shape's solidity (area / convex hull area, measured on the lattice) is what the scene bounds
    assert solidity(lattice_block(np.zeros(2), np.array([0.2, 0.1]), 0.01), 0.01) == pytest.approx(1.0)
    # and the random particles show it: at the small tier's size (~500-1000 particles a blob; the smoke
    # tier's ~80 are too few to tell a bay from the seeding's gaps) their hull has bays, a rectangle's not
    spec = spec.for_tier("small")
    tier = spec.tier("small")
    spacing = 0.5 / tier.params["grid"]
    rng = np.random.default_rng(0)
    for _ in range(4):
        assert _hull_voids(random_block(np.zeros(2), np.array([0.2, 0.2]), spacing, rng), spacing) < 0.01
    for i in range(4):
        scene = build_scene(spec, tier, material_params(spec)[1], np.random.default_rng(i))
        assert _hull_voids(scene.position, spacing) > 0.03


def test_context_values_cycle_over_the_test_trajectories(smoke_dataset: Callable[[str], Path]) -> None:
    spec = load_domain_spec("continuous-heldout")
    trajectories = load_split(smoke_dataset("continuous-heldout"), "test")
    angles = [float(t.step_context[0, 0]) for t in trajectories]
    assert angles == list(spec.context.values[: len(trajectories)])
    base = load_split(smoke_dataset("continuous"), "test")[0]  # the same scene, another friction angle
    assert np.array_equal(trajectories[0].position[0], base.position[0])
    assert base.step_context[0, 0] != angles[0]
    assert not np.array_equal(trajectories[0].position[-1], base.position[-1])


def test_shaken_box_moves_its_walls_along_x_and_keeps_water_and_cube_inside(
        smoke_dataset: Callable[[str], Path]) -> None:
    spec = load_domain_spec("boxbath-shake")
    dx, room = spec.solver_params["particle_spacing"], 0.5 * (1 - spec.scene["container_width"])
    for traj in load_split(smoke_dataset("boxbath-shake"), "train"):
        pos, types = traj.position.astype(np.float64), traj.particle_type
        walls, water, cube = (pos[:, types == t] for t in (KINEMATIC_PARTICLE_TYPE, 5, 0))
        shift = walls - walls[0]
        assert np.all(shift[..., 1:] == 0.0) and np.allclose(shift[..., 0], shift[:, :1, 0], atol=1e-6)
        offset = shift[:, 0, 0]  # A sin(w t): the whole container, rigidly, along x only
        assert 0.01 < np.abs(offset).max() <= room * (spec.bounds[0][1] - spec.bounds[0][0]) + 1e-6
        left, right = walls[..., 0].min(axis=1), walls[..., 0].max(axis=1)
        for body in (water, cube):  # between the moving walls, half a spacing off them (the box projection)
            assert np.all(body[..., 0].min(axis=1) >= left + dx / 2 - 1e-4)
            assert np.all(body[..., 0].max(axis=1) <= right - dx / 2 + 1e-4)
        rest = np.linalg.norm(cube[0][:, None] - cube[0][None], axis=-1)
        for frame in cube:
            assert np.allclose(np.linalg.norm(frame[:, None] - frame[None], axis=-1), rest, rtol=0.01, atol=1e-6)
