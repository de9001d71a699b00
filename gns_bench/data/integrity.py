"""Before a run reads a dataset: every split it will read is valid, and the data are the data `metadata.json`
describes (its `content_hash`), so a changed file cannot pass for the original in a run key or a table.

Hashing reads every array of every split (a few seconds for a cpu-tier dataset); the check is cached in
`<dataset>/.content_hash_verified.json` by each split file's size and modification time, so it is paid once per
change of the files. A dataset whose files were changed on purpose is re-hashed with `gns-bench rehash DIR`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from gns_bench.data.format import (
    SPLITS,
    DatasetError,
    Metadata,
    check_split,
    content_hashes,
    read_metadata,
    write_json_atomic,
)

VERIFIED_FILE = ".content_hash_verified.json"


def _file_stamps(dataset_dir: Path) -> dict[str, list[int]]:
    stamps = {}
    for split in SPLITS:
        path = dataset_dir / f"{split}.h5"
        if path.is_file():
            stat = path.stat()
            stamps[split] = [stat.st_size, stat.st_mtime_ns]
    return stamps


def verify_content_hash(dataset_dir: str | os.PathLike, meta: Metadata | None = None) -> str | None:
    """The dataset's `content_hash`, checked against its files (cached by size and modification time). Raises
    `DatasetError` naming the split(s) that changed; None when metadata.json holds no hash (nothing to check)."""
    dataset_dir = Path(dataset_dir)
    meta = meta or read_metadata(dataset_dir)
    if meta.content_hash is None:
        return None
    stamps = _file_stamps(dataset_dir)
    cache = dataset_dir / VERIFIED_FILE
    try:
        cached = json.loads(cache.read_text())
        if cached.get("content_hash") == meta.content_hash and cached.get("files") == stamps:
            return meta.content_hash
    except (OSError, ValueError):
        pass
    whole, hashes = content_hashes(dataset_dir)
    if whole != meta.content_hash:
        recorded = meta.extra.get("split_hashes") or {}
        changed = [split for split in hashes if recorded.get(split) not in (None, hashes[split])]
        gone = [split for split in recorded if split not in hashes]
        which = "; ".join(([f"split(s) {', '.join(changed)} changed"] if changed else [])
                          + ([f"split(s) {', '.join(gone)} missing"] if gone else [])) or (
            "the arrays changed (this dataset records no per-split hashes to say which split)")
        raise DatasetError(dataset_dir / "metadata.json",
                           f"content_hash {meta.content_hash[:12]}... does not match the data: {which}. A run on "
                           "it would be recorded as the original. If the change was on purpose, re-hash it: "
                           f"gns-bench rehash {dataset_dir}", field="content_hash")
    try:
        write_json_atomic(cache, {"content_hash": meta.content_hash, "files": stamps})
    except OSError:  # a read-only dataset: checked again next time
        pass
    return meta.content_hash


def rehash(dataset_dir: str | os.PathLike) -> str:
    """Record the dataset's current content in metadata.json (`content_hash`, `split_hashes`): for files changed
    on purpose. Statistics are not recomputed."""
    dataset_dir = Path(dataset_dir)
    data = json.loads((dataset_dir / "metadata.json").read_text())
    data["content_hash"], data["split_hashes"] = content_hashes(dataset_dir)
    write_json_atomic(dataset_dir / "metadata.json", data)
    (dataset_dir / VERIFIED_FILE).unlink(missing_ok=True)
    return data["content_hash"]


def check_before_run(dataset_dir: str | os.PathLike, meta: Metadata, *, needed: tuple[str, ...],
                     min_length: int) -> None:
    """Everything a run will read, checked before it creates anything: the splits it needs (`needed`: present
    and valid) and any other split present (valid), one trajectory in memory at a time; then the content hash."""
    dataset_dir = Path(dataset_dir)
    for split in SPLITS:  # first, so that a damaged file is named with its trajectory and field
        if split in needed or (dataset_dir / f"{split}.h5").exists():
            check_split(dataset_dir, split, meta, min_length=min_length)
    verify_content_hash(dataset_dir, meta)
