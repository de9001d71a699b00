"""Domain specs: all 16 paper domains declared, validated with errors naming file and key."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest

from gns_bench.physics.mpm import simulate
from gns_bench.physics.spec import (
    SpecError,
    UnknownDomainError,
    list_domains,
    load_domain_spec,
    load_spec_file,
)

# Table 1 (App. C.4): simulator, max particles, sequence length, one-step MSE (x1e-9), rollout MSE (x1e-3)
KNOWL5 = {
    "water-3d": ("sph", 3, 13000, 800, 8.66, 10.1),
    "sand-3d": ("mpm", 3, 20000, 350, 1.42, 0.554),
    "goop-3d": ("mpm", 3, 14000, 300, 1.32, 0.618),
    "water-3d-s": ("sph", 3, 5800, 800, 9.66, 9.52),
    "boxbath": ("pbd", 3, 1000, 150, 54.5, 4.2),
    "water": ("mpm", 2, 1900, 1000, 2.82, 17.4),
    "sand": ("mpm", 2, 2000, 320, 6.23, 2.37),
    "goop": ("mpm", 2, 1900, 400, 2.91, 1.89),
    "multimaterial": ("mpm", 2, 2000, 1000, 1.81, 16.9),
    "fluidshake": ("mpm", 2, 1300, 2000, 2.10, 20.1),
    "waterdrop": ("mpm", 2, 1000, 1000, 1.52, 7.01),
    "waterdrop-xl": ("mpm", 2, 7100, 1000, 1.23, 14.9),
    "waterramps": ("mpm", 2, 2300, 600, 4.91, 11.6),
    "sandramps": ("mpm", 2, 3300, 400, 2.77, 2.07),
    "randomfloor": ("mpm", 2, 3400, 600, 2.77, 6.72),
    "continuous": ("mpm", 2, 4300, 400, 2.06, 1.06),
}
MPM_DOMAINS = [d for d, row in KNOWL5.items() if row[0] == "mpm"]


@pytest.mark.parametrize("domain", MPM_DOMAINS)
def test_mpm_spec_matches_paper_table(domain: str) -> None:
    solver, dim, max_particles, length, one_step, rollout = KNOWL5[domain]
    spec = load_domain_spec(domain)
    assert (spec.solver, spec.dim) == (solver, dim)
    assert spec.paper.max_particles == max_particles and spec.paper.sequence_length == length
    assert math.isclose(spec.paper.one_step_mse, one_step * 1e-9, rel_tol=1e-9)
    assert math.isclose(spec.paper.rollout_mse, rollout * 1e-3, rel_tol=1e-9)
    paper = spec.tier("paper")
    assert paper.sequence_length == length and paper.params["max_particles"] == max_particles
    smoke = spec.tier("smoke")
    assert 20 <= smoke.sequence_length <= 40 and sum(smoke.trajectories.values()) <= 4
    assert set(spec.materials) <= set(spec.particle_types)


def test_every_domain_loads() -> None:
    domains = list_domains()
    assert set(MPM_DOMAINS) <= set(domains)
    for domain in domains:
        spec = load_domain_spec(domain)
        assert spec.id == domain and len(spec.bounds) == spec.dim
        # the stored dt keeps particles moving a small fraction of R per frame (released WaterDrop: ~1e-3, R/15)
        assert spec.dt <= 0.01


def _broken_copy(tmp_path: Path, old: str, new: str) -> Path:
    text = load_domain_spec("waterdrop").path.read_text()
    assert old in text
    path = tmp_path / "waterdrop.toml"
    path.write_text(text.replace(old, new, 1))
    return path


@pytest.mark.parametrize("old, new, key", [
    ("dt = 0.0025", "", "dt"),
    ('solver = "mpm"', 'solver = "fem"', "solver"),
    ("connectivity_radius = 0.015", "connectivity_radius = -1.0", "connectivity_radius"),
    ("bounds = [[0.1, 0.9], [0.1, 0.9]]", "bounds = [[0.1, 0.9]]", "bounds"),
    ("[tiers.small]\nsequence_length = 1000", "[tiers.small]\nsequence_length = 5",
     "tiers.small.sequence_length"),
    ("particle_types = { water = 5 }", "particle_types = { water = 12 }", "particle_types.water"),
])
def test_spec_errors_name_file_and_key(tmp_path: Path, old: str, new: str, key: str) -> None:
    path = _broken_copy(tmp_path, old, new)
    with pytest.raises(SpecError) as info:
        load_spec_file(path)
    assert str(path) in str(info.value) and f"'{key}'" in str(info.value)


def test_unknown_domain_lists_known_ones() -> None:
    with pytest.raises(UnknownDomainError) as info:
        load_domain_spec("no-such-domain")
    message = str(info.value)
    assert message.startswith("unknown domain 'no-such-domain'") and "<file>" not in message
    assert all(domain in message for domain in ("waterdrop", "sand-3d", "boxbath", "waterramps-long"))
    assert info.value.domains == list_domains()


def test_continuous_friction_angle_excludes_held_out_interval_from_train_only() -> None:
    spec = load_domain_spec("continuous")
    assert spec.context is not None and spec.context.name == "friction_angle"
    rng = np.random.default_rng(0)
    train = np.array([spec.for_split("train").context.sample(rng) for _ in range(2000)])
    test = np.array([spec.for_split("test").context.sample(rng) for _ in range(2000)])
    held_out = (train > 30.0) & (train < 55.0)
    assert not held_out.any()
    assert train.min() >= 0.0 and train.max() <= 80.0
    # uniform over [0, 30] U [55, 80]: both pieces are 30 and 25 degrees long
    assert abs(np.mean(train < 30.0) - 30 / 55) < 0.04
    assert 0.2 < np.mean((test > 30.0) & (test < 55.0)) < 0.4  # 25/80 of the test draws fall inside


@pytest.mark.parametrize("section, key", [("scene", "blokcs"), ("mpm", "cfll")])
def test_mpm_rejects_unknown_solver_and_scene_keys(section: str, key: str) -> None:
    spec = load_domain_spec("waterdrop")
    if section == "scene":
        spec = dataclasses.replace(spec, scene={**spec.scene, key: 1})
    else:
        spec = dataclasses.replace(spec, solver_params={**spec.solver_params, key: 1})
    with pytest.raises(ValueError, match=f"'{section}.{key}'"):
        simulate(spec, "smoke", np.random.default_rng(0))


@pytest.mark.parametrize("key, value, expected", [
    ("block_size", [0.3, 0.1], "[min, max] with min <= max"),
    ("blocks", [1.5, 2], "[min, max] with min <= max (ints)"),
    ("on_floor", "yes", "true or false"),
    ("initial_speed", -1.0, "a number >= 0.0"),
    ("block_materials", ["lava"], "of the spec's materials"),
    ("random_floor", 2.5, "a whole number of segments"),
])
def test_a_scene_key_of_the_wrong_kind_is_refused_naming_file_and_key(key: str, value, expected: str) -> None:
    """`scenes.scene_spec` types every `[scene]` key once; a tier's override is named as the tier's."""
    from gns_bench.physics.scenes import SceneSpec, scene_spec

    spec = load_domain_spec("waterramps")
    tier = spec.tier("smoke")
    assert scene_spec(spec, tier).container_width == SceneSpec.container_width == 0.7  # unset: the one default
    bad = dataclasses.replace(tier, params={**tier.params, "scene": {**tier.params.get("scene", {}), key: value}})
    with pytest.raises(ValueError, match=re.escape(f"{spec.path}: key 'tiers.smoke.scene.{key}'") + ".*"
                       + re.escape(expected)):
        scene_spec(spec, bad)
