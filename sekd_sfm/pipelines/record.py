"""What a run writes: the names of its files, and its record (``stats.json``) read back typed.

An output folder of ``sekd reconstruct`` (``--extend`` adds to it in place)::

    features.h5, pairs.txt, matches.h5   the earlier stages (``--conf`` names the two files hloc-style)
    features-refined.h5                  the keypoints the database got (``refined_name``)
    database.db, colmap.log              COLMAP's database and log
    model/, models/<k>/                  the largest model, the others largest first
    georef.json                          the local east-north-up frame, when the model was georeferenced
    stats.json                           the record: status, configuration, versions, counts, timings

``sekd triangulate`` writes the same names for the files it shares. Every other module learns
about an earlier run through this one: ``Record.from_record(OUT)`` (the record, checked, with
the typed configuration and the paths of its files), ``read_record`` / ``write_record``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ..errors import SekdError
from ..files.atomic import write_json
from ..stages.mapping import MAIN_MODEL
from .config import DEFAULT_FILE_NAMES, ReconstructConfig, config_from_dict

STATS = "stats.json"
PAIRS = "pairs.txt"
DATABASE = "database.db"
COLMAP_LOG = "colmap.log"
GEOREF = "georef.json"
MODEL = MAIN_MODEL
MODELS = "models"


def refined_name(features_name: str) -> str:
    """The refined keypoints' file name beside the features': features.h5 -> features-refined.h5."""
    path = Path(features_name)
    return f"{path.stem}-refined{path.suffix or '.h5'}"


def write_record(stats: dict, folder: Path) -> Path:
    """Write ``stats`` as the record of the run in ``folder`` (atomically); returns its path."""
    return write_json(stats, Path(folder) / STATS)


def read_record(folder: Path) -> dict | None:
    """The record of the run in ``folder`` as a dict, or None when there is none (missing, unreadable, not a
    JSON object)."""
    try:
        data = json.loads((Path(folder) / STATS).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def record_path(folder: Path) -> Path:
    """Where the record of the run in ``folder`` is (for messages that name it)."""
    return Path(folder) / STATS


@dataclass(frozen=True)
class Record:
    """The record of a ``sekd reconstruct`` run in ``out``: ``data`` as written, with typed views of it."""

    out: Path
    data: dict

    @classmethod
    def from_record(cls, out: str | Path, *, needs: str = "config") -> Record:
        """The record in ``out``; SekdError (one sentence) when there is none or it lacks the key ``needs``."""
        out = Path(out)
        data = read_record(out)
        if data is None:
            raise SekdError(f"{out}: not an output folder of `sekd reconstruct` (no readable {STATS}); "
                            "give the folder `sekd reconstruct PHOTOS -o OUT` wrote")
        if needs == "config" and (not isinstance(data.get("config"), dict) or "features" not in data["config"]):
            raise SekdError(f"{out / STATS}: not the record of `sekd reconstruct` (no config.features); "
                            "give the folder `sekd reconstruct` wrote")
        if needs not in ("config", "") and needs not in data:
            raise SekdError(f"{out / STATS}: not the record of `sekd reconstruct` (no {needs})")
        return cls(out, data)

    @property
    def path(self) -> Path:
        return self.out / STATS

    @property
    def finished(self) -> bool:
        """The run succeeded and its main model is on disk."""
        return self.data.get("status") == "ok" and (self.out / MODEL / "images.bin").is_file()

    @property
    def config_data(self) -> dict:
        """The configuration as recorded (JSON types)."""
        return self.data.get("config") or {}

    def config(self, weights: str | None = None) -> ReconstructConfig:
        """The configuration the run used, typed; ``weights``: the SEKD network's file (records leave it out)."""
        return config_from_dict(self.config_data, weights)

    @property
    def inputs(self) -> dict:
        """The files given instead of made (``features``, ``matches``: paths or None)."""
        return self.data.get("inputs") or {}

    @property
    def file_names(self) -> tuple[str, str]:
        return tuple(self.config_data.get("file_names") or DEFAULT_FILE_NAMES)

    @property
    def features(self) -> Path:
        """The feature file the model's keypoints index: the one given to the run, or the one it made in ``out``."""
        given = self.inputs.get("features")
        return Path(given) if given else self.out / self.file_names[0]

    @property
    def refined(self) -> Path:
        """The refined keypoints the run made in ``out`` (present when refinement was on)."""
        return self.out / refined_name(self.file_names[0])

    @property
    def images_dir(self) -> str | None:
        """The photo folder as the run was given it (relative to where it ran, or absolute)."""
        return self.data.get("images_dir")

    @property
    def masks(self) -> str | None:
        return self.config_data.get("masks")

    @property
    def matching(self) -> dict:
        """The match file's configuration as the run recorded it (defaults resolved), or {}."""
        return self.data.get("matching") or {}
