"""What a run writes: the names of its files, and its record (``stats.json``) read back typed.

An output folder of ``sekd reconstruct`` (``--extend`` adds to it in place)::

    features.h5, pairs.txt, matches.h5   the earlier stages (``--conf`` names the two files hloc-style)
    features-refined.h5                  the keypoints the database got (``refined_name``)
    database.db, colmap.log              COLMAP's database and log
    model/, models/<k>/                  the largest model, the others largest first
    georef.json                          the local east-north-up frame, when the model was georeferenced
    images/, views/, view-masks/         videos' keyframes; panoramas' views (and masks), the other photos linked
    rig.json, panoramas.txt              the rigs with their poses; each panorama's pose
    stats.json                           the record: status, configuration, versions, counts, timings

``sekd triangulate`` writes the same names for the files it shares. Every other module learns
about an earlier run through this one: ``Record.from_record(OUT)`` (the record, checked, with
the typed configuration and the paths of its files), ``read_record`` / ``write_record``; and
``Record.of_model(MODEL)``: the record of the run that wrote a model, with the photo and mask
folders it was given (``photo_folder``, ``masks_folder``; relative ones found from where it ran).
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
#: The photos of a run whose input holds videos: their keyframes (``stages.keyframes``), the input's photos linked.
IMAGES = "images"
#: Panoramas' perspective views and their masks (``stages.panoramas``), the input's other photos linked.
VIEWS, VIEW_MASKS = "views", "view-masks"
#: The rig file a run used (``stages.rig``): as given, with the poses it estimated filled in.
RIG = "rig.json"
#: One line per posed panorama, hloc's format (``stages.panoramas``).
PANORAMA_POSES = "panoramas.txt"
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
    def from_record(cls, out: str | Path, *, needs: str = "config", option: str = "") -> Record:
        """The record in ``out``; SekdError (one sentence) when there is none or it lacks the key ``needs``.
        ``option``: the command-line option that named ``out`` (``--reference``), for the message."""
        out, give = Path(out), f"give {option} the folder" if option else "give the folder"
        data = read_record(out)
        if data is None:
            raise SekdError(f"{out}: not an output folder of `sekd reconstruct` (no readable {STATS}); "
                            f"{give} `sekd reconstruct PHOTOS -o OUT` wrote")
        if needs == "config" and (not isinstance(data.get("config"), dict) or "features" not in data["config"]):
            raise SekdError(f"{out / STATS}: not the {STATS} of `sekd reconstruct` (no config.features); "
                            f"{give} `sekd reconstruct` wrote")
        if needs not in ("config", "") and needs not in data:
            raise SekdError(f"{out / STATS}: not the {STATS} of `sekd reconstruct` (no {needs})")
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

    @classmethod
    def of_model(cls, model: str | Path) -> Record | None:
        """The record of the run that wrote the model folder ``model`` (``OUT/model`` or ``OUT/models/<k>``): the
        first readable record naming a photo folder, in the model's parent folder or the one above; None if none."""
        model = Path(model)
        for out in (model.parent, model.parent.parent):
            data = read_record(out)
            if data is not None and "images_dir" in data:
                return cls(out, data)
        return None

    def folder(self, value: str) -> Path:
        """A folder the record names, found from here (``recorded_folder``)."""
        return recorded_folder(value, self.out, self.data)

    def photo_folder(self) -> Path | None:
        """The photo folder the run was given, found from here (``recorded_folder``); None when it recorded none."""
        return self.folder(str(self.images_dir)) if self.images_dir else None

    def masks_folder(self) -> Path | None:
        """The mask folder the run was given (``config.masks``), found from here; None when it had no masks."""
        return self.folder(self.masks) if self.masks else None


def recorded_folder(value: str, out: Path, data: dict) -> Path:
    """A folder named in the record ``data`` of the run in ``out``: absolute as is; relative, from where the run
    ran, else from the current folder (the first of the two that exists)."""
    path = Path(value)
    if path.is_absolute():
        return path
    base = _run_directory(out, data)
    candidates = ([base / path] if base is not None else []) + [path]
    return next((c for c in candidates if c.is_dir()), candidates[0])


def _run_directory(out: Path, data: dict) -> Path | None:
    """The working folder the run in ``out`` ran in, from ``out`` and the model path it recorded (``output``,
    relative to that folder): recorded folders that are relative are relative to it."""
    recorded = Path(str(data.get("output", "")))
    if recorded.is_absolute() or not recorded.parts:
        return None
    relative_out = recorded.parent.parts
    out = Path(out).resolve()
    if not relative_out:
        return out
    if ".." in relative_out or out.parts[-len(relative_out):] != relative_out:
        return None
    return out.parents[len(relative_out) - 1]
