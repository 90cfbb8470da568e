"""The paper's Table 4 ablations with our own training: which checkpoints to compare.

An ablation run is the baseline recipe with one switch on (``no_affine``, ``no_desc_dis``,
``no_desc_rep``, ``no_det_rep``) and possibly fewer rounds. To compare like with like, the
baseline is represented by its best step model (by the run's own validation) within the
same number of rounds, and each ablation by its best step model.

``python -m sekd_sfm.train.ablation BASELINE ABLATION_RUN ...`` prints one
``LABEL=sekd:PATH`` per line, the methods of ``sekd bench``.
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from ..errors import SekdError
from .config import RUNTIME_FIELDS, TrainConfig, differing_fields, load_run_config
from .report import ranked_steps, rounds_done

SWITCHES = ("no_affine", "no_desc_dis", "no_desc_rep", "no_det_rep")
# Fields that may differ between an ablation and its baseline: the switches themselves, the
# number of rounds (compared at equal rounds), and where and how fast it ran.
FREE_FIELDS = {*SWITCHES, "rounds", "images", "init_weights", *RUNTIME_FIELDS}


@dataclasses.dataclass(frozen=True)
class Candidate:
    label: str
    task: str
    path: Path
    value: float


def best_step(run: Path, max_round: int | None = None, metric: str | None = None) -> tuple[str, float]:
    """(task, value) of the best validated training step of ``run`` with round <= ``max_round``.

    The metric is the run's ``best_metric`` unless given; the untrained start never counts.
    """
    ranked = ranked_steps(run, max_round, metric)
    if not ranked:
        raise SekdError(f"{run}: no validated step{'' if max_round is None else f' in rounds 0-{max_round}'} yet")
    return ranked[0]


def switches_on(config: TrainConfig) -> list[str]:
    return [name for name in SWITCHES if getattr(config, name)]


def check_same_recipe(baseline: TrainConfig, ablation: TrainConfig, where: Path) -> None:
    """SekdError unless ``ablation`` = ``baseline`` + exactly one switch (rounds and hardware aside)."""
    differ = differing_fields(baseline, ablation, ignore=FREE_FIELDS)
    if differ:
        raise SekdError(f"{where}: not the baseline's recipe ({', '.join(differ)} differ); "
                        "start ablations with the baseline's config file")
    if len(switches_on(ablation)) != 1 or switches_on(baseline):
        raise SekdError(f"{where}: an ablation has exactly one switch on (found {switches_on(ablation) or 'none'}); "
                        f"the baseline none (found {switches_on(baseline) or 'none'})")


def ablation_candidates(baseline: Path, ablations: list[Path]) -> list[Candidate]:
    """The baseline at the ablations' number of rounds, then each finished ablation's best step."""
    base_config = load_run_config(Path(baseline) / "config.yaml")
    chosen, rounds = [], set()
    for run in ablations:
        config = load_run_config(Path(run) / "config.yaml")
        check_same_recipe(base_config, config, run)
        if rounds_done(run) < config.rounds:
            raise SekdError(f"{run}: {rounds_done(run)} of {config.rounds} rounds done; finish it with "
                            f"sekd evolve --resume --out {run}")
        task, value = best_step(run, metric=base_config.best_metric)
        chosen.append(Candidate(f"ours_{switches_on(config)[0]}", task, Path(run) / "models" / f"{task}.pth", value))
        rounds.add(config.rounds)
    if len(rounds) > 1:
        raise SekdError(f"ablations trained for different numbers of rounds ({sorted(rounds)}): compare equal rounds")
    max_round = (rounds.pop() if rounds else base_config.rounds) - 1
    if rounds_done(baseline) <= max_round:
        raise SekdError(f"{baseline}: {rounds_done(baseline)} rounds done, the ablations had {max_round + 1}")
    task, value = best_step(baseline, max_round)
    return [Candidate("ours_full", task, Path(baseline) / "models" / f"{task}.pth", value), *chosen]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("baseline", type=Path, help="run folder of the full recipe")
    parser.add_argument("ablations", type=Path, nargs="*", help="run folders of the ablations")
    args = parser.parse_args(argv)
    try:
        candidates = ablation_candidates(args.baseline, args.ablations)
    except SekdError as exc:
        raise SystemExit(f"Error: {exc}") from None
    for c in candidates:
        print(f"{c.label}=sekd:{c.path}")


if __name__ == "__main__":
    main()
