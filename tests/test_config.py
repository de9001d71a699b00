"""Typed configuration: defaults are the paper's, overrides are typed, errors name source and key."""

from __future__ import annotations

from pathlib import Path

import pytest

from gns_bench.config import ConfigError, load_config

PACKAGED = Path(__file__).resolve().parent.parent / "gns_bench" / "configs"


def test_defaults_are_the_papers() -> None:
    c = load_config()
    assert (c.model.message_passing_steps, c.model.latent_size, c.model.mlp_hidden_layers) == (10, 128, 2)
    assert c.model.input_sequence_length == 6 and c.model.particle_type_embedding_size == 16
    assert not c.model.shared_processor and c.model.position_encoding == "relative"
    assert (c.train.batch_size, c.train.learning_rate, c.train.noise_std) == (2, 1e-4, 3e-4)
    assert load_config(PACKAGED / "paper.toml") == c


def test_overrides_are_typed() -> None:
    c = load_config(None, ["model.message_passing_steps=5", "train.noise_std=6.7e-4", "model.self_edges=true",
                           "model.position_encoding=absolute", "model.connectivity_radius=0.02"])
    assert c.model.message_passing_steps == 5 and c.train.noise_std == 6.7e-4 and c.model.self_edges is True
    assert c.model.position_encoding == "absolute" and c.model.connectivity_radius == 0.02
    assert c.flat()["model.message_passing_steps"] == 5


@pytest.mark.parametrize(
    "override, message",
    [("model.message_passing_step=5", "unknown key 'model.message_passing_step'"),
     ("model.latent_size=big", "model.latent_size: expected int"),
     ("model.position_encoding=polar", "expected one of"),
     ("train.noise_std=-1", "train.noise_std: must be >= 0"),
     ("train.position_correction=1.5", "must be in \\[0, 1\\]"),
     ("optim.lr=1", "unknown section \\[optim\\]"),
     ("model.latent_size", "has no value: write section.key=value")],
)
def test_bad_values_name_the_key(override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


def test_bad_file_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[model]\nlatent_size = 0\n")
    with pytest.raises(ConfigError, match=f"{path}.*model.latent_size: must be > 0"):
        load_config(path)
    path.write_text("[model\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_config(path)
