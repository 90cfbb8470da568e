"""Stage 5: database -> COLMAP model(s), by pycolmap's incremental mapper.

Output layout under the output folder::

    model/            the largest sub-model (most registered images), COLMAP binary format
    submodels/1, ...  the other sub-models, if any, largest first
"""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from tqdm import tqdm

from ..errors import Interrupted
from .colmap import open_database, require_pycolmap, set_options

MAIN_MODEL = "model"
SUBMODELS = "submodels"


def mapper_options(assignments: list[str] | None = None, seed: int = 0):
    """IncrementalPipelineOptions with validated ``key=value`` overrides, seeded for repeatable runs.

    One thread unless ``num_threads=N`` is assigned: COLMAP's mapper repeats its model for a
    seed only on one thread. With all cores, bundle adjustment sums in a varying order and on
    a weak scene that decides what registers (sacre_coeur, same matches: 10/10 images in three
    runs of four, 3/10 in the other; on one thread 10/10 every time). Mapping is the cheap
    stage here (seconds for tens of images); ``--mapper num_threads=-1`` trades repeatability
    for speed on large scenes.
    """
    pycolmap = require_pycolmap()
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    options.num_threads = 1
    return set_options(options, assignments or [], "--mapper")


class _MapperProgress:
    """A progress bar driven by the mapper's callbacks: +2 at an initial pair, +1 per registered image."""

    def __init__(self, total: int, enabled: bool):
        self.bar = tqdm(total=total, unit="img", desc="mapping", disable=not enabled, dynamic_ncols=True)
        self.models = 0

    def initial_pair(self) -> None:
        self.models += 1
        self.bar.set_postfix_str(f"model {self.models}")
        self._advance(2)

    def next_image(self) -> None:
        self._advance(1)

    def _advance(self, n: int) -> None:
        # Sub-models may share images, so the count can exceed the image total: cap it.
        self.bar.update(max(0, min(n, self.bar.total - self.bar.n)))


def run_mapper(database: str | Path, image_dir: str | Path, options=None, progress: bool = True) -> list:
    """Incremental mapping of ``database``; the reconstructions found, largest first (may be empty).

    ``image_dir`` is only read for point colours. The random generator is seeded from
    ``options.random_seed`` (``pycolmap.set_random_seed``) so a run is repeatable.
    """
    pycolmap = require_pycolmap()
    options = options or mapper_options()
    pycolmap.set_random_seed(max(0, options.random_seed))
    with open_database(database) as db:
        total = db.num_images()
    bar = _MapperProgress(total, progress)
    scratch = Path(tempfile.mkdtemp(prefix="mapping-", dir=Path(database).parent))
    try:
        found = pycolmap.incremental_mapping(str(database), str(image_dir), str(scratch), options,
                                             initial_image_pair_callback=bar.initial_pair,
                                             next_image_callback=bar.next_image)
    except KeyboardInterrupt:  # pycolmap stops the mapper at Ctrl-C and raises it here
        raise Interrupted(f"interrupted while mapping: {database} (features and matches) is kept; run the same "
                          "command again to map again") from None
    finally:
        bar.bar.close()
        shutil.rmtree(scratch, ignore_errors=True)  # models are written by write_models, in our layout
    return sorted(found.values(), key=lambda r: (-r.num_reg_images(), -r.num_points3D()))


def write_models(reconstructions: list, output_dir: str | Path) -> list[Path]:
    """Write the largest reconstruction to ``output_dir/model`` and the others to ``submodels/<k>``.

    COLMAP binary format. Stale models of an earlier run are removed first. Returns the folders written.
    """
    output_dir = Path(output_dir)
    for stale in (output_dir / MAIN_MODEL, output_dir / SUBMODELS):
        shutil.rmtree(stale, ignore_errors=True)
    paths = [output_dir / MAIN_MODEL] + [output_dir / SUBMODELS / str(k) for k in range(1, len(reconstructions))]
    for reconstruction, path in zip(reconstructions, paths):
        path.mkdir(parents=True, exist_ok=True)
        reconstruction.write_binary(str(path))
    return paths[: len(reconstructions)]


def registered_names(reconstruction) -> list[str]:
    """Names of the images with a pose in ``reconstruction``, sorted."""
    return sorted(reconstruction.image(i).name for i in reconstruction.reg_image_ids())


def model_stats(reconstruction) -> dict:
    """Registered images, 3D points, mean track length (observations per point), mean reprojection error (px)."""
    return {
        "registered_images": int(reconstruction.num_reg_images()),
        "points3D": int(reconstruction.num_points3D()),
        "mean_track_length": float(reconstruction.compute_mean_track_length()),
        "mean_observations_per_image": float(reconstruction.compute_mean_observations_per_reg_image()),
        "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
    }
