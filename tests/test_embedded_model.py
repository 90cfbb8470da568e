"""The model shipped inside the package, and the step that ships it."""
import re
from pathlib import Path

import h5py
import pytest
from click.testing import CliRunner
from conftest import GRAFFITI, ROOT
from sekd_sfm.cli.main import sekd

from sekd_sfm.errors import SekdError
from sekd_sfm.train import ship
from sekd_sfm.weights import EMBEDDED_MODEL, file_sha256, load_model

RUN = ROOT / "pipelines/train_default/run"


def test_embedded_model_loads_with_the_papers_parameter_count():
    net, info = load_model()  # no weights: the embedded default
    assert info.path == str(EMBEDDED_MODEL)
    assert sum(p.numel() for p in net.parameters()) == 661_762
    assert EMBEDDED_MODEL.stat().st_size < 3_000_000
    assert info.meta["schedule"] == "cpu" and info.meta["seed"] == 0 and "command" in info.meta


def test_model_card_checksum_is_the_embedded_files():
    card = (ROOT / "docs/model_card.md").read_text()
    assert re.search(r"SHA-256 \| `([0-9a-f]{64})`", card).group(1) == file_sha256(EMBEDDED_MODEL, 64)


def test_embedded_model_estimates_graffiti_1_2(shared):
    """Regression guard, not a benchmark: the easiest viewpoint pair within 3 px mean corner error."""
    assert ship.graffiti_corner_error() < 3.0


def test_ship_refuses_a_checkpoint_that_fails_the_guard(tmp_path, shared):
    # r2_b of the first run validates better than r2_d but misses v_graffiti 1-2 (3.84 px).
    with pytest.raises(SekdError, match="v_graffiti 1-2 mean corner error"):
        ship.ship_model(RUN, tmp_path / "m.pth", which="models/r2_b.pth")
    assert not (tmp_path / "m.pth").exists()


def test_extract_without_weights_uses_the_embedded_model(tmp_path, shared):
    images = tmp_path / "images"
    images.mkdir()
    (images / "1.ppm").write_bytes((GRAFFITI / "1.ppm").read_bytes())
    result = CliRunner().invoke(sekd, ["extract", str(images), "-o", str(tmp_path / "f.h5"), "--resize-max", "320",
                                       "--no-progress"])
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "f.h5") as f:
        assert f.attrs["model_sha256"] == file_sha256(EMBEDDED_MODEL)
        assert f["1.ppm/keypoints"].shape[0] > 100


def test_training_wall_time_sums_each_process_run(tmp_path):
    log = tmp_path / "train.log"
    log.write_text(
        "2026-01-01 10:00:00,000 INFO new run in /x: 1 process(es)\n"
        "2026-01-01 10:30:00,500 INFO round 0 ...\n"
        "Traceback lines without a time stamp are ignored\n"
        "2026-01-03 09:00:00,000 INFO resumed run in /x: 1 process(es)\n"
        "2026-01-03 09:15:00,000 INFO validation\n")
    assert ship.training_wall_seconds(log) == 45 * 60
    assert ship.training_wall_seconds(log, until="round 0") == 30 * 60  # up to a model: stops at its line
    assert ship.training_wall_seconds(log, until="never logged") == 45 * 60


def test_ship_copies_the_best_model_and_writes_its_card(tmp_path, shared):
    dest = ship.ship_model(RUN, tmp_path / "m.pth", tmp_path / "card.md", guard=False)
    net, info = load_model(dest)
    best = load_model(RUN / "best.pth")[0].state_dict()
    assert all((net.state_dict()[k] == v).all() for k, v in best.items())
    assert info.meta["data"] == "../shared/data/train/coco" and info.meta["wall_seconds"] > 0
    card = (tmp_path / "card.md").read_text()
    assert file_sha256(dest, 64) in card and "--schedule cpu --seed 0" in card


def test_ship_refuses_a_model_over_the_size_limit(tmp_path, monkeypatch):
    monkeypatch.setattr(ship, "MAX_BYTES", 1000)
    with pytest.raises(SekdError, match="over 1000"):
        ship.ship_model(RUN, tmp_path / "m.pth")
    assert not (tmp_path / "m.pth").exists() and not list(Path(tmp_path).iterdir())


@pytest.mark.parametrize("path, shown", [
    ("/elsewhere/work/shared/data/train/coco", "../shared/data/train/coco"),
    ("/data/my_photos", "/data/my_photos"),
    ("relative/photos", "relative/photos"),
])
def test_card_shows_shared_paths_from_any_machine_as_dot_dot_shared(path, shown):
    assert ship._display_path(path) == shown


def test_ship_auto_takes_the_best_validated_step_that_passes_the_guard(monkeypatch):
    errors = {"r2_d": 3.5, "r1_d": float("nan"), "r0_d": 2.0}  # validation ranks r2_d > r1_d > r0_d
    tried = []

    def fake_guard(weights):
        tried.append(Path(weights).stem)
        return errors[Path(weights).stem]

    monkeypatch.setattr(ship, "graffiti_corner_error", fake_guard)
    assert ship.best_guarded_step(RUN) == ("models/r0_d.pth", 2.0)
    assert tried == ["r2_d", "r1_d", "r0_d"]
    errors["r0_d"] = 3.0
    with pytest.raises(SekdError, match="no step model passes the regression guard .*r0_d 3.00 px"):
        ship.best_guarded_step(RUN)


def test_card_names_the_run_a_forked_run_came_from():
    assert ship._fork_rows({"done": []}) == []  # not forked
    state = {"done": [], "forked_from": {"run": "/x/run_v2", "after": "r1_a", "changed": ["spread_weight"]}}
    (row,) = ship._fork_rows(state)
    assert row.startswith("| forked | from `run_v2` after `r1_a`") and "spread_weight" in row
