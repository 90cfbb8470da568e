"""Run a stage in this process: its worker over the batches, results into the part store, one progress bar."""
from __future__ import annotations

from tqdm import tqdm

from ..errors import Interrupted
from ..files import partstore
from .stage import OnError, Stage, calls


def run_local(stage: Stage, parts: partstore.PartStore, on_error: OnError, *, progress: bool = True) -> None:
    """Compute ``stage.batches`` with the stage's worker here; each finished item goes to ``parts``.

    Ctrl-C writes what is finished into the output and raises ``Interrupted`` (the same command
    resumes); any other failure leaves the finished items in ``parts`` for the next run.
    """
    bar = tqdm(total=len(stage.keys), unit=stage.unit, desc=stage.name, disable=not progress, dynamic_ncols=True)
    try:
        worker = stage.build()
        for keys in calls(stage.joinable, stage.batches):
            for key, arrays, error in worker(keys):
                if arrays is None:
                    on_error(key, error)
                else:
                    parts.save(key, arrays)
                bar.update(1)
    except KeyboardInterrupt:
        bar.close()
        saved = partstore.finish_run(stage.output, parts, write_group=stage.write_group, what=stage.items)
        raise Interrupted(f"interrupted: {saved} more {stage.items} saved in {stage.output}; "
                          "run the same command again to resume") from None
    except BaseException:
        partstore.keep_parts(parts)  # finished items stay for the next run
        raise
    finally:
        bar.close()
