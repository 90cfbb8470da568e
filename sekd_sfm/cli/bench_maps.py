"""``sekd bench maps ...``: the benchmarks of what happens to a model after it is built."""
from __future__ import annotations

import click


@click.group()
def maps() -> None:
    """Living-map benchmarks: localize, extend, triangulate, georeference, scored against known cameras.

    \b
    Each writes results.json (with the run's record: version, commit, machine, command) and
    results.md into its output folder.
    """



# The group exists before its commands are added to it.
from sekd_sfm.bench.maps.extend import extend_benchmark

from .georef import georef_benchmark
from .localize import localize_benchmark
from .triangulate import triangulate_benchmark

for _command in (localize_benchmark, extend_benchmark, triangulate_benchmark, georef_benchmark):
    maps.add_command(_command)
