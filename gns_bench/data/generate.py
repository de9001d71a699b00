"""One entry point for datasets by domain id: the built-in `tiny` domain, a physics domain
(`datasets/<id>.toml`) or a variant of one (`datasets/variants/<id>.toml`)."""

from __future__ import annotations

from pathlib import Path

TINY = "tiny"


def dataset_path(domain: str, tier: str, seed: int = 0, data_root: str | Path = "data") -> Path:
    return Path(data_root) / f"{domain}-{tier}-s{seed}"


def ensure_dataset(domain: str, tier: str, seed: int = 0, data_root: str | Path = "data", *,
                   out: str | Path | None = None, progress: bool = True) -> Path:
    """The dataset for (domain, tier, seed): reused when complete, generated (or resumed) otherwise. A
    physics dataset made by an older generator version than its solver's data is stale: `generate_dataset`
    moves it aside (to `<out>.stale-v<version>`, with a message on stderr) and generates it afresh."""
    out = Path(out) if out is not None else dataset_path(domain, tier, seed, data_root)
    complete = (out / "metadata.json").exists()
    if domain == TINY:
        if complete:
            return out
        from gns_bench.data.tiny import generate_tiny

        return generate_tiny(out, tier, seed)
    from gns_bench.physics.generate import generate_dataset, stale_generator_version

    if complete and stale_generator_version(out) is None:
        return out
    return generate_dataset(domain, tier, seed, out, progress=progress)
