"""One entry point for datasets by domain id: the built-in `tiny` domain, a physics domain
(`datasets/<id>.toml`) or a variant of one (`datasets/variants/<id>.toml`)."""

from __future__ import annotations

from pathlib import Path

TINY = "tiny"


def dataset_path(domain: str, tier: str, seed: int = 0, data_root: str | Path = "data") -> Path:
    return Path(data_root) / f"{domain}-{tier}-s{seed}"


def ensure_dataset(domain: str, tier: str, seed: int = 0, data_root: str | Path = "data", *,
                   out: str | Path | None = None, progress: bool = True) -> Path:
    """The dataset for (domain, tier, seed): reused when complete, generated (or resumed) otherwise."""
    out = Path(out) if out is not None else dataset_path(domain, tier, seed, data_root)
    if (out / "metadata.json").exists():
        return out
    if domain == TINY:
        from gns_bench.data.tiny import generate_tiny

        return generate_tiny(out, tier, seed)
    from gns_bench.physics.generate import generate_dataset

    return generate_dataset(domain, tier, seed, out, progress=progress)
