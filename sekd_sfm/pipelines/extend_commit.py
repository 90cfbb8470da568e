"""How an extension (``extend.py``) replaces OUT's files so that a kill at any moment loses nothing.

Everything is staged in ``OUT/extend/`` (``STAGE``): the database copy, the refined keypoints,
the model, the pairs and the record. ``write_journal`` writes the commit's plan
(``OUT/extend/commit.json``) once the staged files are complete and on disk; ``commit`` then
exchanges the staged model folder with ``model/`` atomically (Linux
``renameat2(RENAME_EXCHANGE)``; elsewhere two renames, ``model.backup`` then holds the old one)
and moves the other files over theirs. ``recover`` (the next run, holding the folder's lock)
finishes a commit whose journal exists (roll forward) and discards a stage without one, so
``model/`` is always a complete model: the earlier one until the exchange, the new one from then on.
"""
from __future__ import annotations

import ctypes
import json
import logging
import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from ..files.atomic import write_json
from ..stages.pairs import read_pairs, unique_pairs, write_pairs
from . import record

if TYPE_CHECKING:
    import pycolmap

logger = logging.getLogger("sekd")
#: The staging folder of an extension inside OUT, the commit journal in it, and the earlier model during a swap.
STAGE = "extend"
JOURNAL = "commit.json"
BACKUP = "model.backup"
#: Staged files whose names in OUT differ: the new pairs alone, and the refined keypoints (``record.refined_name``).
NEW_PAIRS = "pairs-new.txt"
REFINED = "refined.h5"


def recover(out: Path) -> None:
    """Finish the commit an earlier run was killed in, then drop whatever else it staged (call it holding the
    folder's lock)."""
    if (out / STAGE / JOURNAL).is_file():  # a commit was interrupted: finish it, then see what is left
        logger.warning("%s: finishing the extension an earlier run was interrupted in", out)
        commit(out)
    shutil.rmtree(out / STAGE, ignore_errors=True)  # an unfinished stage is made again from the start


def stage_model(model: pycolmap.Reconstruction, stage: Path) -> None:
    """Write ``model`` as ``stage/model``, complete on disk before it has that name (a kill leaves no half model)."""
    tmp = stage / "model.tmp"
    tmp.mkdir()
    model.write_binary(str(tmp))
    _fsync_tree(tmp)
    os.rename(tmp, stage / record.MODEL)


def write_journal(stage: Path, out: Path, features_name: str) -> None:
    """The commit's plan, written once every staged file is complete: after it, the extension only rolls forward.

    ``features_name``: OUT's feature file's name, which names the refined keypoints (``record.refined_name``).
    """
    pairs = read_pairs(out / record.PAIRS) if (out / record.PAIRS).is_file() else []
    write_pairs(unique_pairs([*pairs, *read_pairs(stage / NEW_PAIRS)]), stage / record.PAIRS)
    moves = [[record.DATABASE, record.DATABASE], [record.PAIRS, record.PAIRS], [record.STATS, record.STATS]]
    if (stage / REFINED).is_file():
        moves.append([REFINED, record.refined_name(features_name)])
    journal = {"model_inode": (stage / record.MODEL).stat().st_ino, "moves": moves}
    for name in (record.DATABASE, REFINED, record.PAIRS, record.STATS):
        if (stage / name).is_file():
            _fsync(stage / name)
    write_json(journal, stage / JOURNAL)
    _fsync(stage / JOURNAL)
    _fsync(stage)


def commit(out: Path) -> None:
    """Carry out (or finish) the journal's commit; every step can be repeated after a kill."""
    stage = out / STAGE
    journal = json.loads((stage / JOURNAL).read_text())
    model, staged = out / record.MODEL, stage / record.MODEL
    new_in_place = model.is_dir() and model.stat().st_ino == journal["model_inode"]
    if not new_in_place and not (model.is_dir() and staged.is_dir() and _exchange(staged, model)):
        _swap_by_renames(model, staged, out / BACKUP)
    if staged.is_dir():  # the earlier model, after the exchange
        shutil.rmtree(out / BACKUP, ignore_errors=True)
        os.rename(staged, out / BACKUP)
    for source, target in journal["moves"]:
        if (stage / source).is_file():
            _drop_sqlite_sidecars(out / target)  # the earlier file's (read-only opens leave them)
            os.replace(stage / source, out / target)
    _drop_sqlite_sidecars(out / record.DATABASE)
    _fsync(out)
    shutil.rmtree(out / BACKUP, ignore_errors=True)  # the new model is complete: the backup can go
    (stage / JOURNAL).unlink()
    shutil.rmtree(stage, ignore_errors=True)


def _drop_sqlite_sidecars(path: Path) -> None:
    """Remove ``path``'s SQLite -wal/-shm files: once the staged database (settled, no log of its own) replaces
    ``path`` they belong to the earlier file, which nothing uses any more, and must not be applied to the new one."""
    if path.name.endswith(".db"):
        for suffix in ("-wal", "-shm"):
            path.with_name(path.name + suffix).unlink(missing_ok=True)


def _swap_by_renames(model: Path, staged: Path, backup: Path) -> None:
    """Where directories cannot be exchanged atomically: model -> backup, staged -> model (a kill in between
    leaves the earlier model in ``backup`` and the new one staged; the next run finishes the swap)."""
    if model.is_dir():
        shutil.rmtree(backup, ignore_errors=True)
        os.rename(model, backup)
    os.rename(staged, model)


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap two directories in one step (Linux renameat2 RENAME_EXCHANGE); False where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    logger.info("renameat2 exchange unavailable (errno %d): two renames instead", ctypes.get_errno())
    return False


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(folder: Path) -> None:
    for path in folder.iterdir():
        _fsync(path)
    _fsync(folder)
