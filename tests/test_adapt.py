"""`sekd adapt`: fine-tuning on the user's photos writes a model extract accepts, resumes after a kill,
refuses bad input in one line; `reconstruct --adapt` extracts with the adapted model."""
import json
import os
import signal
import subprocess
import sys
import time

import h5py
import pytest
import torch
from click.testing import CliRunner
from test_train_run import write_small_coco

from sekd_sfm.cli.main import sekd
from sekd_sfm.model.weights import EMBEDDED_MODELS, file_sha256, load_model
from sekd_sfm.train.adapt import AdaptConfig, adapt_tasks, run_folder, train_config

TINY = ["--schedule", "tiny", "--from", "own", "--no-progress", "--num-threads", "1"]


@pytest.fixture(scope="module")
def photos(shared, tmp_path_factory):
    return write_small_coco(tmp_path_factory.mktemp("photos4"), 4)


@pytest.fixture(scope="module")
def adapted(photos, tmp_path_factory):
    """One tiny adaptation of the embedded `own` model on 4 photos (a few seconds)."""
    out = tmp_path_factory.mktemp("adapt") / "model.pth"
    result = CliRunner().invoke(sekd, ["adapt", str(photos), "-o", str(out), *TINY])
    assert result.exit_code == 0, result.output
    return out


def _one_error_line(result, pattern: str) -> None:
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: ") and pattern in lines[0], result.output


def test_adapt_writes_a_changed_model_that_extract_accepts(adapted, photos, tmp_path):
    net, info = load_model(adapted)
    start = load_model(EMBEDDED_MODELS["own"])[0].state_dict()
    assert any(not torch.equal(v, start[k]) for k, v in net.state_dict().items())  # it trained
    record = info.meta["adapted"]
    assert record["count"] == 4 and record["start"] == "own" and record["rounds"] == 1
    assert record["start_sha256"] == file_sha256(EMBEDDED_MODELS["own"], 64)
    state = json.loads((run_folder(adapted) / "state.json").read_text())
    assert state["done"] == ["r1_a", "r1_b", "r1_c", "r1_d"]
    result = CliRunner().invoke(sekd, ["extract", str(photos), "-o", str(tmp_path / "f.h5"), "--weights",
                                       str(adapted), "--no-progress"])
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "f.h5") as f:
        assert f.attrs["model_sha256"] == file_sha256(adapted)
        assert len(f.keys()) == 4


def test_auto_schedule_sees_every_photo_with_epochs_sized_to_the_collection(photos):
    small, large = (train_config(photos, n, AdaptConfig(start="own")) for n in (20, 200))
    assert (small.epochs_desc, small.epochs_det) == (8, 4) and (large.epochs_desc, large.epochs_det) == (2, 1)
    assert small.subset_factor == 1 and not small.validate and small.init_weights == str(EMBEDDED_MODELS["own"])
    assert [t.id for t in adapt_tasks(2)] == ["r1_a", "r1_b", "r1_c", "r1_d", "r2_a", "r2_b", "r2_c", "r2_d"]


def test_killed_adapt_resumes_to_the_same_model(adapted, photos, tmp_path):
    out = tmp_path / "model.pth"
    state = run_folder(out) / "state.json"
    command = [sys.executable, "-m", "sekd_sfm.cli.main", "adapt", str(photos), "-o", str(out), *TINY]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               env={**os.environ, "OMP_NUM_THREADS": "1"})
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and process.poll() is None:
        if state.is_file() and json.loads(state.read_text())["done"]:
            break  # the first task is saved
        time.sleep(0.02)
    process.send_signal(signal.SIGKILL)
    process.wait()
    done = json.loads(state.read_text())["done"]
    assert 1 <= len(done) < 4 and not out.exists(), done  # killed in the middle
    again = CliRunner().invoke(sekd, ["adapt", str(photos), "-o", str(out), "--resume", "--no-progress"])
    _one_error_line(CliRunner().invoke(sekd, ["adapt", str(photos), "-o", str(out), *TINY]), "already exists")
    assert again.exit_code == 0, again.output
    assert len(json.loads(state.read_text())["done"]) == 4
    resumed, uninterrupted = load_model(out)[0].state_dict(), load_model(adapted)[0].state_dict()
    # Every draw is seeded per task, so the model is the uninterrupted one, up to float noise between
    # processes (measured: at most 2e-6 per weight).
    assert all(torch.allclose(v, uninterrupted[k], atol=1e-5) for k, v in resumed.items())
    assert "resumed run" in (run_folder(out) / "train.log").read_text()


def test_adapt_refuses_bad_input_in_one_line(photos, tmp_path):
    run = CliRunner().invoke
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_error_line(run(sekd, ["adapt", str(empty), "-o", str(tmp_path / "m.pth")]), "no images found")
    _one_error_line(run(sekd, ["adapt", str(tmp_path / "absent"), "-o", str(tmp_path / "m.pth")]),
                    "photo folder not found")
    _one_error_line(run(sekd, ["adapt", str(photos), "-o", str(tmp_path / "m.pth"), "--from", str(tmp_path / "x.pth")]),
                    "neither own nor authors nor an existing checkpoint file")
    _one_error_line(run(sekd, ["adapt", str(photos), "-o", str(tmp_path / "m.pth"), "--resume"]),
                    "no adaptation to resume")
    started = tmp_path / "s.pth"
    run_folder(started).mkdir()
    (run_folder(started) / "state.json").write_text("{}")
    _one_error_line(run(sekd, ["adapt", str(photos), "-o", str(started)]), "continue it with --resume")
    assert not (tmp_path / "m.pth").exists()


def test_reconstruct_adapt_extracts_with_the_adapted_model(adapted, photos, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "adapted.pth").write_bytes(adapted.read_bytes())  # made by an earlier run: reused, not redone
    result = CliRunner().invoke(sekd, ["reconstruct", str(photos), "-o", str(out), "--adapt", "--no-progress",
                                       "--resize-max", "128"])
    with h5py.File(out / "features.h5") as f:  # 4 unrelated photos make no model; the features are made
        assert f.attrs["model_sha256"] == file_sha256(adapted)
    assert result.exit_code in (0, 1)
    _one_error_line(CliRunner().invoke(sekd, ["reconstruct", str(photos), "-o", str(out), "--adapt", "--feature",
                                              "sift"]), "--adapt fine-tunes a SEKD model")
