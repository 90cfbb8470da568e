"""Choosing the checkpoints of the Table 4 ablations: equal rounds, same recipe, best step."""
import json
from dataclasses import replace
from pathlib import Path

import pytest

from sekd_sfm.errors import SekdError
from sekd_sfm.train.ablation import ablation_candidates, best_step
from sekd_sfm.train.config import TrainConfig


def make_run(root: Path, name: str, scores: dict[str, float], **fields) -> Path:
    """A run folder with a config, a state whose done list follows ``scores`` and their validation."""
    run = root / name
    run.mkdir()
    config = replace(TrainConfig(), images="photos", best_metric="mma3", **fields)
    (run / "config.yaml").write_text(config.to_yaml())
    rows = [{"task": t, "round": -1 if t == "start" else int(t[1]), "mma3": v, "ha_avg": 1 - v}
            for t, v in scores.items()]
    (run / "metrics.json").write_text(json.dumps(rows))
    (run / "state.json").write_text(json.dumps({"done": list(scores)}))
    return run


def test_best_step_within_rounds_never_the_start(tmp_path):
    run = make_run(tmp_path, "base", {"start": 0.9, "r0_d": 0.1, "r1_b": 0.3, "r1_d": 0.2, "r2_b": 0.5, "r2_d": 0.4})
    assert best_step(run) == ("r2_b", 0.5)
    assert best_step(run, max_round=1) == ("r1_b", 0.3)
    assert best_step(run, max_round=0) == ("r0_d", 0.1)
    assert best_step(run, max_round=1, metric="ha_avg") == ("r0_d", 0.9)


def test_candidates_compare_the_baseline_at_the_ablations_rounds(tmp_path):
    base = make_run(tmp_path, "base", {"start": 0.1, "r0_d": 0.1, "r1_b": 0.3, "r1_d": 0.2, "r2_b": 0.5, "r2_d": 0.4},
                    rounds=5)
    aff = make_run(tmp_path, "no_affine", {"start": 0.1, "r0_d": 0.15, "r1_b": 0.2, "r1_d": 0.25},
                   rounds=2, no_affine=True)
    chosen = ablation_candidates(base, [aff])
    assert [(c.label, c.task, c.value) for c in chosen] == [("ours_full", "r1_b", 0.3),
                                                           ("ours_no_affine", "r1_d", 0.25)]
    assert chosen[1].path == aff / "models" / "r1_d.pth"


@pytest.mark.parametrize("fields, message", [
    ({"rounds": 2, "no_affine": True, "lr": 1e-4}, "lr differ"),
    ({"rounds": 2}, "exactly one switch"),
    ({"rounds": 2, "no_affine": True, "no_det_rep": True}, "exactly one switch"),
    ({"rounds": 3, "no_affine": True}, "1 of 3 rounds done"),
])
def test_candidates_refuse_what_is_not_comparable(tmp_path, fields, message):
    base = make_run(tmp_path, "base", {"r0_d": 0.1, "r1_d": 0.2}, rounds=5)
    ablation = make_run(tmp_path, "abl", {"r0_d": 0.1, "r1_d": 0.2} if fields["rounds"] == 2 else {"r0_d": 0.1},
                        **fields)
    with pytest.raises(SekdError, match=message):
        ablation_candidates(base, [ablation])


def test_candidates_refuse_a_baseline_with_fewer_rounds(tmp_path):
    base = make_run(tmp_path, "base", {"r0_d": 0.1}, rounds=5)
    ablation = make_run(tmp_path, "abl", {"r0_d": 0.1, "r1_d": 0.2}, rounds=2, no_desc_rep=True)
    with pytest.raises(SekdError, match="1 rounds done, the ablations had 2"):
        ablation_candidates(base, [ablation])
