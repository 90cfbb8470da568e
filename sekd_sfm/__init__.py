"""sekd_sfm: SEKD learned local features for COLMAP reconstruction.

Data flows images -> features.h5 -> pairs -> matches.h5 -> database -> model -> report;
each stage is one function taking paths and a configuration and returning the path it
wrote, and the ``sekd`` CLI only parses options. The public API is importable from here,
so modules can move without breaking callers::

    from sekd_sfm import FeatureConfig, extract_features, make_pairs, match_features, reconstruct

Packages, in the order data flows through them: ``model/`` (the network, SEKD-Lite, weights,
inference, the embedded checkpoints), ``files/`` (feature and match files, the crash-safe part
store, shards, locking, images), ``execution/`` (local and Ray executors of a stage), the stages
``extract``, ``pairs``, ``match``, then ``sfm/`` (database, verification, mapping, export),
``train/``, ``bench/``, and ``evaluation/`` (metrics and readers both of those use).

The names below are imported on first use (PEP 562), so ``import sekd_sfm`` stays light and
``sekd --help`` does not load torch.
"""
from __future__ import annotations

import importlib

__version__ = "0.2.0"

#: Public name -> the module that defines it.
_EXPORTS = {
    "SekdError": "sekd_sfm.errors",
    "Interrupted": "sekd_sfm.errors",
    # stage 1: images -> features.h5
    "FeatureConfig": "sekd_sfm.features",
    "FEATURE_TYPES": "sekd_sfm.features",
    "build_extractor": "sekd_sfm.features",
    "extract_features": "sekd_sfm.stages.extract",
    "SEKDConfig": "sekd_sfm.model.inference",
    "load_model": "sekd_sfm.model.weights",
    "SEKDNet": "sekd_sfm.model.network",
    # the files
    "list_keys": "sekd_sfm.files.features",
    "read_features": "sekd_sfm.files.features",
    "read_matches": "sekd_sfm.files.matches",
    "list_pairs": "sekd_sfm.files.matches",
    "list_images": "sekd_sfm.files.images",
    # stage 2: features.h5 -> pairs.txt
    "PairsConfig": "sekd_sfm.stages.pairs",
    "make_pairs": "sekd_sfm.stages.pairs",
    "read_pairs": "sekd_sfm.stages.pairs",
    "write_pairs": "sekd_sfm.stages.pairs",
    # stage 3: features.h5 + pairs.txt -> matches.h5
    "MatchConfig": "sekd_sfm.stages.match",
    "match_features": "sekd_sfm.stages.match",
    "match_descriptors": "sekd_sfm.stages.match",
    # where stages run
    "RayOptions": "sekd_sfm.execution",
    # the rest of the pipeline
    "ReconstructConfig": "sekd_sfm.pipelines.reconstruct",
    "reconstruct": "sekd_sfm.pipelines.reconstruct",
    "relative_pose": "sekd_sfm.pipelines.relpose",
    "RelposeConfig": "sekd_sfm.pipelines.relpose",
    # after the first model: extend (reconstruct(..., extend=ExtendOptions())), localize, triangulate, GPS
    "ExtendOptions": "sekd_sfm.pipelines.extend",
    "localize": "sekd_sfm.pipelines.localize",
    "LocalizeConfig": "sekd_sfm.pipelines.localize",
    "triangulate": "sekd_sfm.pipelines.triangulate",
    "TriangulateConfig": "sekd_sfm.pipelines.triangulate",
    "GpsConfig": "sekd_sfm.stages.georef",
    "read_poses": "sekd_sfm.files.poses",
    "shared_dir": "sekd_sfm.runtime",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'sekd_sfm' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value  # next time without this call
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
