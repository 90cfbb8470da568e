"""The models shipped inside the package (ours and the authors'), --model, and the step that ships ours."""
import re
from pathlib import Path

import h5py
import pytest
from click.testing import CliRunner
from conftest import GRAFFITI, ROOT

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.model.weights import (
    DEFAULT_MODEL,
    EMBEDDED_MODEL,
    EMBEDDED_MODELS,
    file_sha256,
    load_model,
)
from sekd_sfm.train import ship

OWN = EMBEDDED_MODELS["own"]
AUTHORS = EMBEDDED_MODELS["authors"]
#: sha256 of sekd_authors.pth: the authors' released tensors, re-saved once; they never change.
AUTHORS_SHA256 = "0dd03b04fe6cb24c39381bfd8e6526d712f87586f56a516bad1cd5f2d7b03341"

# The text files of a finished 3-round run of the `cpu` schedule (config, state, log,
# validation, label history); its checkpoints are made by the `run` fixture.
RUN_FILES = ROOT / "tests/data/ship_run"


@pytest.fixture
def run(tmp_path) -> Path:
    """A run folder: RUN_FILES, best.pth = our embedded model, step models = an untrained network."""
    import shutil

    import torch

    from sekd_sfm.model.network import SEKDNet

    folder = tmp_path / "run"
    shutil.copytree(RUN_FILES, folder)
    (folder / "models").mkdir()
    shutil.copy(OWN, folder / "best.pth")
    torch.manual_seed(0)
    untrained = {"state_dict": SEKDNet().state_dict(), "sekd_sfm": {}}
    for task in ("r0_d", "r1_d", "r2_d", "untrained"):
        torch.save(untrained, folder / "models" / f"{task}.pth")
    return folder


@pytest.mark.parametrize("name", ["own", "authors"])
def test_embedded_models_load_with_the_papers_parameter_count(name):
    net, info = load_model(EMBEDDED_MODELS[name])
    assert sum(p.numel() for p in net.parameters()) == 661_762
    assert EMBEDDED_MODELS[name].stat().st_size < 3_000_000
    if name == "own":
        assert info.meta["schedule"] == "cpu" and info.meta["seed"] == 0 and "command" in info.meta
    else:
        assert info.sha256 == AUTHORS_SHA256[:16] and "Alibaba" in info.meta["license"]


def test_default_model_is_an_embedded_one():
    _, info = load_model()  # no weights: the default
    assert info.path == str(EMBEDDED_MODEL) == str(EMBEDDED_MODELS[DEFAULT_MODEL])


@pytest.mark.parametrize("name, card", [("own", "docs/model_card.md"), ("authors", "docs/model_card_authors.md")])
def test_model_card_checksum_is_the_embedded_files(name, card):
    text = (ROOT / card).read_text()
    assert re.search(r"SHA-256 \| `([0-9a-f]{64})`", text).group(1) == file_sha256(EMBEDDED_MODELS[name], 64)


def test_authors_model_is_their_release_unchanged_with_its_licence(shared):
    import torch

    release = shared / "weights/sekd/sekd.pth"
    ours = torch.load(AUTHORS, weights_only=True)
    theirs = torch.load(release, map_location="cpu", weights_only=True)["state_dict"]
    assert ours["state_dict"].keys() == theirs.keys()
    assert all(torch.equal(ours["state_dict"][k], v) for k, v in theirs.items())
    assert ours["sekd_sfm"]["source_sha256"] == file_sha256(release, 64)
    assert file_sha256(release, 64) in (ROOT / "docs/model_card_authors.md").read_text()  # the card names the release
    licence = (AUTHORS.parent / "LICENSE-authors.txt").read_text()
    assert (shared / "weights/sekd/LICENSE").read_text() in licence


@pytest.mark.parametrize("name", ["own", "authors"])
def test_embedded_models_estimate_graffiti_1_2(shared, name):
    """Regression guard, not a benchmark: the easiest viewpoint pair within 3 px mean corner error."""
    assert ship.graffiti_corner_error(EMBEDDED_MODELS[name]) < 3.0


def test_ship_refuses_a_checkpoint_that_fails_the_guard(tmp_path, shared, run):
    # An untrained network misses v_graffiti 1-2 by hundreds of pixels.
    with pytest.raises(SekdError, match="v_graffiti 1-2 mean corner error"):
        ship.ship_model(run, tmp_path / "m.pth", which="models/untrained.pth")
    assert not (tmp_path / "m.pth").exists()


def test_ship_measures_the_guard_even_when_the_checkpoint_records_one(tmp_path, shared, run):
    import torch

    # A copied shipped model's metadata carries its old guard error; the weights here are untrained.
    checkpoint = torch.load(run / "models" / "untrained.pth", weights_only=True)
    checkpoint["sekd_sfm"] = {"graffiti_1_2_corner_error": 0.5}
    torch.save(checkpoint, run / "models" / "stale.pth")
    with pytest.raises(SekdError, match="v_graffiti 1-2 mean corner error"):
        ship.ship_model(run, tmp_path / "m.pth", which="models/stale.pth")
    assert not (tmp_path / "m.pth").exists()


@pytest.fixture
def one_image(tmp_path) -> Path:
    images = tmp_path / "images"
    images.mkdir()
    (images / "1.ppm").write_bytes((GRAFFITI / "1.ppm").read_bytes())
    return images


@pytest.mark.parametrize("model", [None, "own", "authors"])
def test_extract_model_option_picks_the_embedded_file(tmp_path, shared, one_image, model):
    args = ["extract", str(one_image), "-o", str(tmp_path / "f.h5"), "--resize-max", "320", "--no-progress"]
    result = CliRunner().invoke(sekd, args + (["--model", model] if model else []))
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "f.h5") as f:
        assert f.attrs["model_sha256"] == file_sha256(EMBEDDED_MODELS[model or DEFAULT_MODEL])
        assert f["1.ppm/keypoints"].shape[0] > 100


@pytest.mark.parametrize("extra, message", [
    (["--weights", "{own}"], "--model authors and --weights .* both name the SEKD model; give one of them"),
    (["--feature", "sift"], "--model authors selects a SEKD model; --feature sift does not use it"),
])
def test_model_option_conflicts_are_one_error_line(tmp_path, one_image, extra, message):
    args = ["extract", str(one_image), "-o", str(tmp_path / "f.h5"), "--model", "authors"]
    result = CliRunner().invoke(sekd, args + [e.format(own=OWN) for e in extra])
    assert result.exit_code == 1
    assert len(result.output.strip().splitlines()) == 1 and re.match(f"Error: {message}", result.output), result.output
    assert not (tmp_path / "f.h5").exists()


def test_bench_methods_name_the_embedded_models():
    from sekd_sfm.bench.methods import parse_method

    assert parse_method("sekd:own").weights == str(OWN) and parse_method("sekd:own").label == "sekd_own"
    assert parse_method("ref=sekd:authors").weights == str(AUTHORS)
    assert parse_method("sekd").weights is None  # the default, resolved when loaded


@pytest.mark.parametrize("command", [["reconstruct", "{images}", "-o", "{tmp}/out"], ["relpose", "{img}", "{img}"],
                                     ["bench", "pose", "-o", "{tmp}/b"], ["bench", "homography", "-o", "{tmp}/b"]])
def test_every_model_command_takes_model_and_refuses_both(tmp_path, one_image, command):
    fill = {"images": one_image, "tmp": tmp_path, "img": one_image / "1.ppm"}
    args = [a.format(**fill) for a in command] + ["--model", "own", "--weights", str(AUTHORS)]
    result = CliRunner().invoke(sekd, args)
    assert result.exit_code == 1 and result.output.startswith("Error: --model own and --weights"), result.output
    assert "--model [own|authors|lite]" in CliRunner().invoke(sekd, command[:2] + ["--help"]).output


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


def test_ship_copies_the_best_model_and_writes_its_card(tmp_path, shared, run):
    dest = ship.ship_model(run, tmp_path / "m.pth", tmp_path / "card.md", guard=False)
    net, info = load_model(dest)
    best = load_model(run / "best.pth")[0].state_dict()
    assert all((net.state_dict()[k] == v).all() for k, v in best.items())
    assert info.meta["data"] == "../shared/data/train/coco" and info.meta["wall_seconds"] > 0
    card = (tmp_path / "card.md").read_text()
    assert file_sha256(dest, 64) in card and "--schedule cpu --seed 0" in card


def test_ship_refuses_a_model_over_the_size_limit(tmp_path, monkeypatch, run):
    monkeypatch.setattr(ship, "MAX_BYTES", 1000)
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(SekdError, match="over 1000"):
        ship.ship_model(run, out / "m.pth")
    assert not list(out.iterdir())


@pytest.mark.parametrize("path, shown", [
    ("/elsewhere/work/shared/data/train/coco", "../shared/data/train/coco"),
    ("/data/my_photos", "/data/my_photos"),
    ("relative/photos", "relative/photos"),
])
def test_card_shows_shared_paths_from_any_machine_as_dot_dot_shared(path, shown):
    assert ship._display_path(path) == shown


def test_ship_auto_takes_the_best_validated_step_that_passes_the_guard(monkeypatch, run):
    errors = {"r2_d": 3.5, "r1_d": float("nan"), "r0_d": 2.0}  # validation ranks r2_d > r1_d > r0_d
    tried = []

    def fake_guard(weights):
        tried.append(Path(weights).stem)
        return errors[Path(weights).stem]

    monkeypatch.setattr(ship, "graffiti_corner_error", fake_guard)
    assert ship.best_guarded_step(run) == ("models/r0_d.pth", 2.0)
    assert tried == ["r2_d", "r1_d", "r0_d"]
    errors["r0_d"] = 3.0
    with pytest.raises(SekdError, match="no step model passes the regression guard .*r0_d 3.00 px"):
        ship.best_guarded_step(run)


def test_card_names_the_run_a_forked_run_came_from():
    assert ship._fork_rows({"done": []}) == []  # not forked
    state = {"done": [], "forked_from": {"run": "/x/run_v2", "after": "r1_a", "changed": ["spread_weight"]}}
    (row,) = ship._fork_rows(state)
    assert row.startswith("| forked | from `run_v2` after `r1_a`") and "spread_weight" in row


def test_ship_a_weight_average_of_step_models_names_its_ingredients(tmp_path, shared, run):
    import shutil

    import torch

    from sekd_sfm.train.soup import average_checkpoints

    # Two step models with our embedded weights (files differ by their metadata only), so the
    # 0.75 / 0.25 average is the embedded network exactly and passes the guard.
    shutil.copy(OWN, run / "models" / "r1_d.pth")
    checkpoint = torch.load(OWN, weights_only=True)
    torch.save({"state_dict": checkpoint["state_dict"], "sekd_sfm": {"task": "r2_d"}}, run / "models" / "r2_d.pth")
    soup = average_checkpoints([run / "models/r1_d.pth", run / "models/r2_d.pth"], tmp_path / "soup.pth", [3, 1])
    dest = ship.ship_model(run, tmp_path / "m.pth", card=tmp_path / "card.md", which=str(soup))
    shipped = load_model(dest)[1].meta
    assert [(s["task"], s["weight"]) for s in shipped["average"]] == [("r1_d", 0.75), ("r2_d", 0.25)]
    assert shipped["source"] == "soup.pth" and shipped["schedule"] == "cpu" and "init" not in shipped
    # The average exists once its later ingredient does: the run's time up to r2_d's validation.
    assert shipped["wall_seconds"] == round(ship.training_wall_seconds(run / "train.log", "validation after r2_d"))
    ours = torch.load(OWN, weights_only=True)["state_dict"]
    assert all(torch.equal(v, ours[k]) for k, v in torch.load(dest, weights_only=True)["state_dict"].items())
    card = (tmp_path / "card.md").read_text()
    assert "the weighted average 0.75 x `r1_d` + 0.25 x `r2_d` of the run's step models" in card
    assert f"python -m sekd_sfm.train.soup {run}/models/r1_d.pth {run}/models/r2_d.pth --weights 0.75 0.25" in card


def test_ship_refuses_an_average_with_a_checkpoint_from_elsewhere(tmp_path, run):
    from sekd_sfm.train.soup import average_checkpoints

    soup = average_checkpoints([run / "models/r0_d.pth", AUTHORS], tmp_path / "soup.pth")
    with pytest.raises(SekdError, match="sekd_authors.pth: an ingredient of this weight average is not a step model"):
        ship.ship_model(run, tmp_path / "m.pth", which=str(soup))
    assert not (tmp_path / "m.pth").exists()


def test_starting_model_records_the_lineage_of_a_shipped_model(tmp_path):
    facts = ship.starting_model(str(OWN))
    meta = load_model(OWN)[1].meta
    assert facts["file"] == "sekd_own.pth" and facts["sha256"] == file_sha256(OWN, 64)
    assert facts["shipped_from"] == meta["shipped_from"] and facts["command"] == meta["command"]
    assert ship.starting_model("") is None
    assert ship.starting_model(str(tmp_path / "gone.pth")) == {"file": "gone.pth"}


def test_wall_time_row_adds_every_shipped_starting_model():
    chain = {"wall_seconds": 3600, "init": {"wall_seconds": 7200, "sha256": "x", "file": "a.pth"}}
    assert "after 3.00 h for its starting model(s): 4.50 h from random weights" in ship._wall_row(
        {"wall_seconds": 5400, "init": chain})
    # A link whose time is unknown (a checkpoint that was not shipped): no total is claimed.
    assert "from random weights" not in ship._wall_row({"wall_seconds": 5400, "init": {"sha256": "x", "file": "a.pth"}})


@pytest.fixture
def two_runs(tmp_path, run) -> tuple[Path, Path]:
    """``run`` and ``run_b``, which starts from ``run``'s r1_d; both with an r2_d holding our embedded weights."""
    import shutil

    import torch

    checkpoint = torch.load(OWN, weights_only=True)
    for task in ("r1_d", "r2_d"):  # our weights, other files than the shipped one (their metadata differ)
        torch.save({"state_dict": checkpoint["state_dict"], "sekd_sfm": {"task": task}}, run / "models" / f"{task}.pth")
    run_b = tmp_path / "run_b"
    shutil.copytree(run, run_b, ignore=shutil.ignore_patterns("models"))
    (run_b / "models").mkdir()
    torch.save({"state_dict": checkpoint["state_dict"], "sekd_sfm": {"task": "r2_d", "schedule": "cpu", "seed": 0}},
               run_b / "models" / "r2_d.pth")
    config = (run_b / "config.yaml").read_text().replace("init_weights: ''", f"init_weights: {run}/models/r1_d.pth")
    (run_b / "config.yaml").write_text(config)
    return run, run_b


def test_ship_an_average_of_two_runs_and_a_shipped_model_names_every_run(tmp_path, shared, two_runs):
    import torch

    from sekd_sfm.train.soup import average_checkpoints

    run, run_b = two_runs
    inner = average_checkpoints([run / "models/r2_d.pth", run_b / "models/r2_d.pth"], tmp_path / "inner.pth")
    outer = average_checkpoints([OWN, inner], tmp_path / "v3.pth", [3, 1])
    dest = ship.ship_average([run, run_b], outer, tmp_path / "m.pth", card=tmp_path / "card.md", guard=False)
    meta = load_model(dest)[1].meta
    shares = [(leaf.get("file") or (Path(leaf["run"]).name, leaf["task"]), leaf["weight"]) for leaf in meta["average_of"]]
    assert shares == [("sekd_own.pth", 0.75), (("run", "r2_d"), 0.125), (("run_b", "r2_d"), 0.125)]
    rows = {row["run"]: row for row in meta["runs"]}
    assert rows["run_b"]["init"] == "`r1_d` of `run`" and rows["run"]["init"] == "random weights"
    assert rows["run"]["until"] == "r2_d" and rows["run"]["tasks"][-1] == "r2_d"
    own_seconds = load_model(OWN)[1].meta["wall_seconds"]
    assert meta["wall_seconds"] >= own_seconds + rows["run"]["wall_seconds"] + rows["run_b"]["wall_seconds"] > own_seconds
    assert meta["average_commands"] == [
        "python -m sekd_sfm.train.soup run/models/r2_d.pth run_b/models/r2_d.pth --weights 0.5 0.5 -o inner.pth",
        "python -m sekd_sfm.train.soup sekd_own.pth inner.pth --weights 0.75 0.25 -o v3.pth"]
    assert meta["schedule"] == "cpu" and meta["seed"] == 0 and "command" in meta
    ours = torch.load(OWN, weights_only=True)["state_dict"]  # all ingredients hold it: the average is it, exactly
    assert all(torch.equal(v, ours[k]) for k, v in torch.load(dest, weights_only=True)["state_dict"].items())
    card = (tmp_path / "card.md").read_text()
    assert file_sha256(dest, 64) in card and "| 0.750 | `sekd_own.pth`" in card and "`r1_d` of `run`" in card
    assert "-o v3.pth" in card and "## Runs" in card


def test_ship_average_refuses_an_ingredient_of_unknown_training(tmp_path, two_runs):
    from sekd_sfm.train.soup import average_checkpoints

    run, run_b = two_runs
    soup = average_checkpoints([run / "models/r2_d.pth", AUTHORS], tmp_path / "soup.pth")  # the authors': not shipped here
    with pytest.raises(SekdError, match="sekd_authors.pth: an ingredient of this weight average is neither a step model"):
        ship.ship_average([run, run_b], soup, tmp_path / "m.pth")
    with pytest.raises(SekdError, match="not a weight average"):
        ship.ship_average([run, run_b], run / "models/r2_d.pth", tmp_path / "m.pth")
    assert not (tmp_path / "m.pth").exists()


def test_ship_command_names_several_runs_and_fails_with_one_error_line(tmp_path, two_runs):
    from sekd_sfm.train.soup import average_checkpoints

    run, run_b = two_runs
    soup = average_checkpoints([run / "models/r2_d.pth", AUTHORS], tmp_path / "soup.pth")
    with pytest.raises(SystemExit) as exc:
        ship.main([str(run), str(run_b), "--which", str(soup), "--dest", str(tmp_path / "m.pth")])
    assert str(exc.value).startswith("Error: ") and "\n" not in str(exc.value)
    assert "neither a step model of run, run_b" in str(exc.value) and not (tmp_path / "m.pth").exists()
