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
