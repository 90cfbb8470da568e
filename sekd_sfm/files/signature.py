"""What a derived file was made from, as one string: the input files (size, modification time), the pairs, the
settings. A stage reuses its output, or the finished part of an interrupted run, only under the same signature."""
from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from pathlib import Path


def input_signature(files: Iterable[Path | None], pairs: Iterable[tuple[str, str]], settings: dict) -> str:
    """``files`` (None entries skipped) by name, size and modification time, in order; ``pairs`` as a digest;
    ``settings`` (JSON-serialisable) as they are.

    A file's folder is left out, so a project folder moved or renamed (``mv`` keeps the times) keeps what it
    computed: at 2,000 photos, 330 s of refinement and 730 s of verification."""
    digest = hashlib.sha256("\n".join(f"{a} {b}" for a, b in pairs).encode()).hexdigest()[:16]
    stats = [[p.name, p.stat().st_size, p.stat().st_mtime_ns] for p in map(_path, files) if p is not None]
    return json.dumps({"files": stats, "pairs": digest, "config": settings}, sort_keys=True)


def _path(p: Path | str | None) -> Path | None:
    return None if p is None else Path(p)
