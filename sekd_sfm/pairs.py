"""Stage 2: which image pairs to match (``sekd pairs``): features.h5 -> pairs.txt.

A pair is ``(name0, name1)`` with image keys as in the feature file. Every generator
returns *unique* pairs: duplicates and reversed duplicates ``(b, a)`` of an earlier
``(a, b)`` collapse to the first one seen, and self-pairs ``(a, a)`` are dropped.

Pairs files hold one pair per line, written ``name0<TAB>name1`` so that names with
spaces survive. When reading, a line with a tab is split at the tab; a line without
one is split at whitespace (hloc's and COLMAP's format), which then must give exactly
two names. Blank lines and lines starting with ``#`` are ignored.
"""
from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

from . import featurefile as ff
from .errors import SekdError

logger = logging.getLogger("sekd")
PAIR_MODES = ("exhaustive", "sequential", "from-file")
Pair = tuple[str, str]


@dataclass
class PairsConfig:
    """How to choose pairs: ``mode`` in PAIR_MODES; ``window``/``loop_every`` for sequential; ``file`` for from-file."""

    mode: str = "exhaustive"
    window: int = 10
    loop_every: int = 0
    file: str | None = None


def unique_pairs(pairs) -> list[Pair]:
    """Pairs in first-seen order without duplicates, reversed duplicates or self-pairs."""
    seen: set[frozenset[str]] = set()
    out = []
    for a, b in pairs:
        key = frozenset((a, b))
        if a != b and key not in seen:
            seen.add(key)
            out.append((a, b))
    return out


def exhaustive_pairs(names: list[str]) -> list[Pair]:
    """All ``n (n - 1) / 2`` pairs ``(names[i], names[j])`` with ``i < j``."""
    return unique_pairs((a, b) for i, a in enumerate(names) for b in names[i + 1:])


def natural_key(name: str) -> list:
    """Sort key comparing digit runs as numbers: ``frame_9`` before ``frame_10``."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def sequential_pairs(names: list[str], window: int, loop_every: int = 0) -> list[Pair]:
    """Pairs of a video: each frame with the next ``window`` frames, in natural name order.

    With ``loop_every = K > 0``, every K-th frame (0, K, 2K, ...) is also paired with
    every other K-th frame, so a camera returning to a place is matched (loop closure).
    """
    if window < 1:
        raise SekdError(f"sequential pairs need a window of at least 1 image, got {window}")
    order = sorted(names, key=natural_key)
    pairs = [(a, b) for i, a in enumerate(order) for b in order[i + 1: i + 1 + window]]
    if loop_every > 0:
        keyframes = order[::loop_every]
        pairs += exhaustive_pairs(keyframes)
    return unique_pairs(pairs)


def parse_pair_line(line: str) -> Pair | None:
    """The pair on one line of a pairs file, None for a blank or comment line; ValueError if malformed."""
    line = line.rstrip("\r\n")
    if not line.strip() or line.lstrip().startswith("#"):
        return None
    fields = line.split("\t") if "\t" in line else line.split()
    if len(fields) != 2 or not all(fields):
        raise ValueError(f"expected two names separated by a tab (or by whitespace), got {len(fields)} field(s)")
    return fields[0], fields[1]


def read_pairs(path: str | Path) -> list[Pair]:
    """Unique pairs of a pairs file; SekdError naming the file and line when it cannot be read."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SekdError(f"{path}: cannot read pairs file ({exc}); give a text file with one pair per line") from exc
    pairs = []
    for number, line in enumerate(text.splitlines(), 1):
        try:
            pair = parse_pair_line(line)
        except ValueError as exc:
            raise SekdError(f"{path}:{number}: {exc}; fix the line or remove it") from None
        if pair:
            pairs.append(pair)
    return unique_pairs(pairs)


def format_pairs(pairs: list[Pair]) -> str:
    """Pairs file text: ``name0<TAB>name1`` lines; SekdError for names a pairs file cannot hold."""
    for pair in pairs:
        for name in pair:
            if any(c in name for c in "\t\r\n") or name != name.strip() or not name:
                raise SekdError(f"image name {name!r} cannot be written to a pairs file (tab, newline or edge spaces)")
    return "".join(f"{a}\t{b}\n" for a, b in pairs)


def write_pairs(pairs: list[Pair], path: str | Path) -> Path:
    """Write a pairs file atomically (temporary file, fsync, rename). Returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8", newline="\n") as f:
        f.write(format_pairs(pairs))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def generate_pairs(names: list[str], config: PairsConfig) -> list[Pair]:
    """The pairs ``config`` asks for among ``names`` (a from-file list is read, not filtered)."""
    if config.mode == "exhaustive":
        return exhaustive_pairs(sorted(names))
    if config.mode == "sequential":
        return sequential_pairs(names, config.window, config.loop_every)
    if config.mode == "from-file":
        if not config.file:
            raise SekdError("pairs mode 'from-file' needs a pairs file")
        return read_pairs(config.file)
    raise SekdError(f"unknown pairs mode {config.mode!r}; choose from {', '.join(PAIR_MODES)}")


def make_pairs(features: str | Path, output: str | Path, config: PairsConfig | None = None) -> Path:
    """Write the pairs among the images of the feature file ``features`` to ``output``. Returns ``output``.

    An existing ``output`` with exactly these pairs is left untouched (reused).
    """
    config = config or PairsConfig()
    features, output = Path(features), Path(output)
    ff.read_attrs(features)
    pairs = generate_pairs(ff.list_keys(features), config)
    text = format_pairs(pairs)
    if output.is_file() and output.read_text(encoding="utf-8") == text:
        logger.info("%s: %d pairs, unchanged", output, len(pairs))
        return output
    write_pairs(pairs, output)
    logger.info("%s: %d pairs (%s)", output, len(pairs), config.mode)
    return output
