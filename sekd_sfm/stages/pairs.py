"""Stage 2: which image pairs to match (``sekd pairs``): features.h5 -> pairs.txt.

A pair is ``(name0, name1)`` with image keys as in the feature file. Every generator
returns *unique* pairs: duplicates and reversed duplicates ``(b, a)`` of an earlier
``(a, b)`` collapse to the first one seen, and self-pairs ``(a, a)`` are dropped.

Modes: ``exhaustive`` (all pairs), ``sequential`` (video: a sliding window, optional
keyframe loop closure), ``retrieval`` (each image with its K most similar images by a
global descriptor, see ``retrieval.py``), ``from-file``, and ``auto`` (the default):
exhaustive up to ``2K + 1`` images, where it matches no more pairs than retrieval's
``N * K`` bound, retrieval above (docs/pairs.md has the measurements). Retrieval can be
added to ``sequential`` (loop closure for video) and to ``from-file`` (union).

Pairs files hold one pair per line, ``name0 name1`` separated by one space: the format
COLMAP's pair importer and hloc read. Names containing whitespace (or starting with
``#``, a comment for COLMAP) cannot be written; those images are skipped with one warning.
When reading, older tab-separated lines are still accepted: a line with a tab is split at
the tab, a line without one at whitespace, which then must give exactly two names. Blank
lines and lines starting with ``#`` are ignored.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..files import features as ff
from ..files.atomic import write_atomic
from .retrieval import RetrievalConfig, compute_global_descriptors, nearest_neighbors

logger = logging.getLogger("sekd")
PAIR_MODES = ("auto", "exhaustive", "sequential", "retrieval", "from-file")
DEFAULT_NEIGHBORS = 20
Pair = tuple[str, str]


@dataclass
class PairsConfig:
    """How to choose pairs.

    ``mode`` in PAIR_MODES; ``window``/``loop_every`` for sequential; ``file`` for from-file.
    ``num_neighbors`` K: retrieval neighbours per image. None means 20 for ``retrieval`` and
    ``auto``, and none added to ``sequential``/``from-file``; K > 0 there adds retrieval pairs.
    """

    mode: str = "auto"
    window: int = 10
    loop_every: int = 0
    file: str | None = None
    num_neighbors: int | None = None
    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)


@dataclass(frozen=True)
class GpsNeighbors:
    """Pairs from GPS: each image with its ``k`` nearest images within ``radius_m`` metres.

    ``positions``: metric positions (x, y, z metres, e.g. local ENU) of the images that have one.
    """

    positions: dict[str, tuple[float, float, float]]
    k: int = 10
    radius_m: float = 100.0


def gps_pairs(names: list[str], positions: dict[str, tuple[float, float, float]], k: int,
              radius_m: float) -> list[Pair]:
    """Each of ``names`` that has a position with its ``k`` nearest others within ``radius_m`` (metres).

    Images without a position get no GPS pairs; ties are broken by name, so the pairs are deterministic.
    """
    located = sorted(n for n in names if n in positions)
    if len(located) < 2 or k < 1:
        return []
    xyz = np.array([positions[n] for n in located], np.float64)  # (N, 3) metres
    distances = np.linalg.norm(xyz[:, None] - xyz[None], axis=2)  # (N, N); N is a survey's photos, not millions
    pairs = []
    for i, a in enumerate(located):
        order = np.lexsort((np.arange(len(located)), distances[i]))
        pairs += [(a, located[j]) for j in order if j != i and distances[i, j] <= radius_m][:k]
    return unique_pairs(pairs)


def auto_mode(num_images: int, num_neighbors: int = DEFAULT_NEIGHBORS) -> str:
    """``exhaustive`` while its N (N - 1) / 2 pairs are at most retrieval's N * K (N <= 2K + 1), else ``retrieval``.

    Up to there retrieval saves no matching and could miss pairs; above, exhaustive grows
    as N^2 while retrieval grows as N * K.
    """
    return "exhaustive" if num_images <= 2 * num_neighbors + 1 else "retrieval"


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
        raise ValueError(f"expected two names separated by a space (or a tab), got {len(fields)} field(s)")
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


def unwritable_reason(name: str) -> str | None:
    """Why ``name`` cannot be written to a pairs file (None if it can)."""
    if not name:
        return "empty name"
    if name != name.strip():
        return "leading/trailing space"
    for char, what in (("\n", "newline"), ("\r", "carriage return"), ("\t", "tab")):
        if char in name:
            return what
    if any(c.isspace() for c in name):
        return "space"  # COLMAP and hloc split pair lines at whitespace
    if name.startswith("#"):
        return "starts with '#' (a comment line for COLMAP)"
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return "not valid UTF-8"
    return None


def split_writable(names: list[str]) -> tuple[list[str], dict[str, str]]:
    """(names a pairs file can hold, {other name: why not})."""
    bad = {n: r for n in names if (r := unwritable_reason(n))}
    return [n for n in names if n not in bad], bad


def warn_skipped(bad: dict[str, str]) -> None:
    """One warning line listing the images left out of the pairs and why."""
    if bad:
        listed = ", ".join(f"{name!r} ({why})" for name, why in sorted(bad.items()))
        logger.warning("Warning: skipping %d image(s) whose names COLMAP and hloc pair files cannot hold "
                       "(they split lines at whitespace); rename them to match them: %s", len(bad), listed)


def format_pairs(pairs: list[Pair]) -> str:
    """Pairs file text: ``name0 name1`` lines; SekdError for names a pairs file cannot hold."""
    for pair in pairs:
        for name in pair:
            if reason := unwritable_reason(name):
                raise SekdError(f"image name {name!r} cannot be written to a pairs file ({reason}); rename the image")
    return "".join(f"{a} {b}\n" for a, b in pairs)


def write_pairs(pairs: list[Pair], path: str | Path) -> Path:
    """Write a pairs file atomically (temporary file, fsync, rename). Returns ``path``."""
    path = Path(path)
    try:  # write_atomic creates the folder too
        return write_atomic(path, format_pairs(pairs))
    except OSError as exc:
        raise SekdError(f"{path}: cannot write pairs file ({exc}); free space or choose another output") from exc


def retrieval_pairs(features: Path, names: list[str], config: PairsConfig, num_neighbors: int,
                    progress: bool = True, executor="local") -> list[Pair]:
    """Each of ``names`` with its ``num_neighbors`` most similar images (global descriptors beside ``features``,
    computed on ``executor``)."""
    global_file = compute_global_descriptors(features, config.retrieval, progress=progress, executor=executor)
    neighbours = nearest_neighbors(global_file, names, num_neighbors)
    return unique_pairs((a, b) for a in sorted(names) for b in neighbours[a])


def resolve_mode(config: PairsConfig, num_images: int) -> tuple[str, int]:
    """(concrete mode, retrieval neighbours K to add): ``auto`` decided by the number of images."""
    if config.mode not in PAIR_MODES:
        raise SekdError(f"unknown pairs mode {config.mode!r}; choose from {', '.join(PAIR_MODES)}")
    if config.num_neighbors is not None and config.num_neighbors < 1:
        raise SekdError(f"the number of retrieval neighbours must be at least 1, got {config.num_neighbors}")
    mode = auto_mode(num_images, config.num_neighbors or DEFAULT_NEIGHBORS) if config.mode == "auto" else config.mode
    if mode == "exhaustive":
        return mode, 0
    return mode, config.num_neighbors or (DEFAULT_NEIGHBORS if mode == "retrieval" else 0)


def generate_pairs(names: list[str], config: PairsConfig, features: Path | None = None,
                   progress: bool = True, executor="local") -> list[Pair]:
    """The pairs ``config`` asks for among ``names`` (a from-file list is read, not filtered).

    Retrieval (mode ``retrieval``, or ``num_neighbors`` > 0 with ``sequential``/``from-file``)
    needs the feature file ``features``; its pairs come after the others.
    """
    mode, neighbours = resolve_mode(config, len(names))
    if mode == "exhaustive":
        pairs = exhaustive_pairs(sorted(names))
    elif mode == "sequential":
        pairs = sequential_pairs(names, config.window, config.loop_every)
    elif mode == "from-file":
        if not config.file:
            raise SekdError("pairs mode 'from-file' needs a pairs file")
        pairs = read_pairs(config.file)
    else:
        pairs = []
    if neighbours and len(names) > 1:
        if features is None:
            raise SekdError("retrieval pairs need the feature file")
        pairs += retrieval_pairs(features, names, config, neighbours, progress, executor)
    return unique_pairs(pairs)


def describe_mode(config: PairsConfig, num_images: int) -> str:
    """Human-readable mode for logs, e.g. ``auto -> retrieval K=20, 307 images``."""
    mode, k = resolve_mode(config, num_images)
    text = mode + (f" + retrieval K={k}" if mode in ("sequential", "from-file") and k else
                   f" K={k}" if mode == "retrieval" else "")
    return f"auto -> {text}, {num_images} images" if config.mode == "auto" else text


def make_pairs(features: str | Path, output: str | Path, config: PairsConfig | None = None, *,
               progress: bool = True, gps: GpsNeighbors | None = None, executor="local") -> Path:
    """Write the pairs among the images of the feature file ``features`` to ``output``. Returns ``output``.

    Images whose names a pairs file cannot hold are left out with one warning. An existing
    ``output`` with exactly these pairs is left untouched (reused). ``gps``: GPS neighbour
    pairs added after those of ``config`` (``gps_pairs``); without it the pairs are ``config``'s only.
    ``executor``: where retrieval's global descriptors are computed (a name or an open ``execution.Executor``).
    """
    config = config or PairsConfig()
    features, output = Path(features), Path(output)
    ff.read_attrs(features)
    names, bad = split_writable(ff.list_keys(features))
    pairs = generate_pairs(names, config, features, progress, executor)
    if gps is not None:
        pairs = unique_pairs(pairs + gps_pairs(names, gps.positions, gps.k, gps.radius_m))
    bad.update({n: r for pair in pairs for n in pair if (r := unwritable_reason(n))})  # from a --pairs-file
    warn_skipped(bad)
    pairs = [p for p in pairs if p[0] not in bad and p[1] not in bad]
    text = format_pairs(pairs)
    if output.is_file() and output.read_text(encoding="utf-8", errors="replace") == text:
        logger.info("%s: %d pairs, unchanged", output, len(pairs))
        return output
    write_pairs(pairs, output)
    logger.info("%s: %d pairs (%s%s)", output, len(pairs), describe_mode(config, len(names)),
                f" + GPS neighbours k={gps.k} within {gps.radius_m:g} m" if gps is not None else "")
    return output
