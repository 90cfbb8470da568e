"""What ``sekd reconstruct`` computes: every stage's settings in one typed, recorded configuration.

``ReconstructConfig`` is written into the run's record (``record.STATS``, key ``config``) and read
back typed by ``config_from_dict`` (``--extend`` adds photos with the settings a model was built with).
How a run runs (threads, progress, executor) is not configuration: ``run.RunOptions``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass, field
from typing import Any

from ..features import FeatureConfig
from ..stages.chance import ChanceConfig
from ..stages.database import CameraConfig
from ..stages.georef import GpsConfig
from ..stages.keyframes import KeyframeConfig
from ..stages.match import MatchConfig
from ..stages.modelcheck import ModelCheckConfig
from ..stages.pairs import PairsConfig
from ..stages.refine import RefineConfig
from ..stages.sequence import SequenceConfig
from ..stages.viewgraph import ViewGraphConfig

#: Long side (px) images are reduced to for reconstruction, as hloc does: SEKD's cost grows with
#: the pixels, and a 24 MP photo at full size costs ~40 s of CPU to extract.
DEFAULT_RESIZE_MAX = 1600
#: The mapper used unless told otherwise: ``auto`` = incremental up to 250 photos, hierarchical
#: above (docs/reconstruction.md has the measurements).
DEFAULT_MAPPER = "auto"
#: The feature and match files' names in OUT unless a --conf preset names them.
DEFAULT_FILE_NAMES = ("features.h5", "matches.h5")


@dataclass
class ReconstructConfig:
    """Every stage's settings; ``mapper`` / ``verification`` are ``key=value`` pycolmap option overrides.

    ``mapper_type`` is one of MAPPER_CHOICES; ``mapper`` options are those of its option class
    (for ``auto``: of the mapper it picks for the collection's size).
    """

    features: FeatureConfig = field(default_factory=lambda: FeatureConfig(resize_max=DEFAULT_RESIZE_MAX))
    pairs: PairsConfig = field(default_factory=PairsConfig)
    matching: MatchConfig = field(default_factory=MatchConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    mapper_type: str = DEFAULT_MAPPER
    mapper: list[str] = field(default_factory=list)
    verification: list[str] = field(default_factory=list)
    #: Keypoint refinement between matching and the database (``refine.py``): on the generated
    #: 250-photo block pose AUC@5 0.971 -> 0.980, reprojection error 0.39 -> 0.22 px.
    refine: RefineConfig = field(default_factory=RefineConfig)
    #: Keyframes of the input's videos (``stages.keyframes``): by motion and sharpness, or a fixed count per video.
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    #: Right after verification, drop the verified pairs whose inliers chance alone would give (``stages.chance``:
    #: far-apart photos of like columns verified at 15-25 inliers).
    chance: ChanceConfig = field(default_factory=ChanceConfig)
    #: Between verification and mapping, drop the verified pairs whose relative rotation disagrees with the rest
    #: of the view graph (``stages.viewgraph``: wrong pairs on repeated or symmetric structure).
    view_graph: ViewGraphConfig = field(default_factory=ViewGraphConfig)
    #: After mapping, drop each model's outlying observations (beyond max(0.5 px, 3 robust sigma)) and adjust it
    #: again (``mapper_worker.final_filter``): pose AUC@5 on the generated 250-photo block 0.972 -> 0.993.
    final_filter: bool = True
    #: After mapping, the verified pairs each model's poses contradict (``stages.modelcheck``): a folded model
    #: is said to be one. Reports only; the models are left as they are.
    model_check: ModelCheckConfig = field(default_factory=ModelCheckConfig)
    #: An ordered capture mapped in capture order (``stages.sequence``): the chain of near photos first, the far pairs
    #: that do not fit it dropped; generated walks and a temple with look-alikes, pose AUC@5 0.21-0.49 -> 0.99.
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    seed: int = 0
    #: Names of the feature and match files made in the output folder (``--conf`` names them
    #: hloc-style, feats-<conf>.h5 and matches-<conf>_pairs.h5, so several presets' files coexist).
    file_names: tuple[str, str] = DEFAULT_FILE_NAMES
    #: Folder of masks (``--masks``; photo NAME's is ``masks/NAME.png``, zero = ignore; docs/masks.md), or None.
    #: Recorded as ``config.masks``, where later commands (``sekd export``) find it.
    masks: str | None = None
    #: EXIF GPS (``--gps``, georef.py): ``mode`` auto = GPS neighbour pairs + the model aligned to GPS in a
    #: local ENU frame in metres, when at least 3 photos carry GPS.
    gps: GpsConfig = field(default_factory=GpsConfig)
    #: Camera rigs (``--rig-config``, COLMAP's rig_configurator file; ``stages.rig``), or None.
    rig: str | None = None


def config_dict(config: Any) -> dict:
    """``config`` (a dataclass with a ``features`` FeatureConfig) as its record stores it: the network's path left
    out (a local path; the model's hash is in the feature file)."""
    data = asdict(config)
    data["features"].pop("weights", None)
    return data


def typed(cls: type, data: dict) -> Any:
    """The dataclass ``cls`` from a dict of ``asdict()``, nested dataclasses and tuples restored; keys ``cls``
    lacks (a newer or older record) are ignored, fields ``data`` lacks keep their defaults."""
    values = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default) and isinstance(value, dict):
            value = typed(type(default), value)
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)
        values[f.name] = value
    return cls(**values)


def config_from_dict(data: dict, weights: str | None = None) -> ReconstructConfig:
    """The ReconstructConfig a record's ``config`` describes; ``weights``: the SEKD network's file, which records
    leave out. A record made before the final filter, the view-graph check or the chance check existed has none of
    them (off: its model was made without them, and its extensions are too)."""
    config = typed(ReconstructConfig, {"final_filter": False, "view_graph": {"enabled": False},
                                       "chance": {"enabled": False}, **data})
    config.features.weights = weights
    return config
