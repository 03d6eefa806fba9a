"""The resume state of make-dataset (:mod:`~d2turb.data.generate`): which samples are done (their meta records in
``meta.jsonl`` and the rank shards, with all their files), the merge of the shards, the check that a folder's
finished samples were made with the same settings, and the clean-up after a run that finished none."""

from __future__ import annotations

import json
from pathlib import Path

from d2turb.data.layout import CONFIG_NAME, FILES, META_NAME, SHARD_DIR, file_path, parse_meta_lines
from d2turb.errors import D2TurbError
from d2turb.io import remove_stale_temp_files, write_text


def shard_dir(root: Path) -> Path:
    return Path(root) / SHARD_DIR


def sample_complete(root: Path, sid: str) -> bool:
    return all(file_path(root, kind, sid).is_file() for kind in FILES)


def collect_records(root: Path) -> dict[str, dict]:
    """Meta records (final meta.jsonl and shards) whose files all exist: the samples that are done."""
    root = Path(root)
    paths = [root / META_NAME] + sorted(shard_dir(root).glob("*.jsonl"))
    records: dict[str, dict] = {}
    for path in paths:
        if not path.is_file():
            continue
        for rec in parse_meta_lines(path.read_bytes()):
            if rec["id"] not in records and sample_complete(root, rec["id"]):
                records[rec["id"]] = rec
    return records


def remove_temp_files(root: Path) -> int:
    """Temporary files a killed writer left in the dataset's folders (see ``d2turb.io.remove_stale_temp_files``)."""
    return sum(remove_stale_temp_files(Path(root) / kind) for kind in (*FILES, SHARD_DIR, "."))


def merge_meta(root: Path) -> int:
    """Rank 0, after all ranks finished: sorted, de-duplicated meta.jsonl; shards removed."""
    root = Path(root)
    records = collect_records(root)
    lines = "".join(json.dumps(r, sort_keys=True) + "\n" for r in sorted(records.values(), key=lambda r: r["index"]))
    write_text(root / META_NAME, lines)
    for p in shard_dir(root).glob("*.jsonl"):
        p.unlink()
    if shard_dir(root).is_dir():
        shard_dir(root).rmdir()
    return len(records)


def check_same_config(root: Path, record: dict) -> bool:
    """Whether ``dataset.json`` must be (re)written: it is absent, or the folder holds no finished sample yet
    (a run that wrote no sample does not lock the folder to its settings). Raises ``D2TurbError`` when
    finished samples were made with other settings."""
    path = Path(root) / CONFIG_NAME
    if not path.is_file():
        return True
    try:
        old = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        old = None
    keys = "version pairs patch split bins seed batch depth params geometry sources frames sequence camera".split()
    keys += ["profile", "field"]  # the field profile (absent from the other datasets' configs)
    diff = keys if not isinstance(old, dict) else [k for k in keys if old.get(k) != record.get(k)]
    if not diff:
        return False
    if not collect_records(root):
        return True
    if not isinstance(old, dict):
        raise D2TurbError(f"{path}: unreadable dataset config, but the folder holds samples; use a new --out")
    raise D2TurbError(f"{root} holds a dataset made with different settings ({', '.join(diff)}); use a new --out")


def reset_unfinished(root: Path) -> None:
    """Remove what an earlier run that finished no sample left (its config, meta shards, sample files)."""
    root = Path(root)
    (root / CONFIG_NAME).unlink(missing_ok=True)
    (root / META_NAME).unlink(missing_ok=True)
    for p in shard_dir(root).glob("*.jsonl"):
        p.unlink()
    for kind, suffix in FILES.items():
        for p in (root / kind).glob(f"{'[0-9]' * 7}{suffix}"):
            p.unlink()


def discard_if_empty(root: Path, created_root: bool) -> None:
    """After a failed single-process run: if no sample was finished, remove the config and empty folders
    it made, so a corrected re-run starts afresh (nothing is removed once a sample exists)."""
    if collect_records(root):
        return
    reset_unfinished(root)
    for folder in [shard_dir(root), *(root / kind for kind in FILES), *([root] if created_root else [])]:
        try:
            folder.rmdir()  # only when empty
        except OSError:
            pass
