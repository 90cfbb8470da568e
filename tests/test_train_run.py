"""Whole runs: tiny self-evolving training improves matching, exports usable models, resumes exactly,
reports user errors in one line, and runs data-parallel over two processes."""
import json
import os
import subprocess
import sys

import cv2
import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import SHARED

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.model.weights import load_model
from sekd_sfm.runtime import tuning_requested, untune_allocator
from sekd_sfm.train import labels as labels_module
from sekd_sfm.train.config import TrainConfig, load_run_config, resolve_config
from sekd_sfm.train.evolve import RunFolder, Runner, evolve, train_one_step
from sekd_sfm.train.report import validation_position
from sekd_sfm.train.steps import HalfwayDrop, _optimiser


def write_small_coco(folder, count: int, long_side: int = 128):
    """The first ``count`` shared COCO photos, downscaled (area) to ``long_side``."""
    folder.mkdir(parents=True, exist_ok=True)
    for path in sorted((SHARED / "data/train/coco").glob("*.jpg"))[:count]:
        image = cv2.imread(str(path))
        h, w = image.shape[:2]
        s = long_side / max(h, w)
        small = cv2.resize(image, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(folder / path.name), small)
    return folder


@pytest.fixture(scope="module")
def images16(shared, tmp_path_factory):
    return write_small_coco(tmp_path_factory.mktemp("coco16"), 16)


@pytest.fixture(scope="module")
def images8(shared, tmp_path_factory):
    return write_small_coco(tmp_path_factory.mktemp("coco8"), 8)


@pytest.fixture(scope="module")
def tiny_run(images16, tmp_path_factory):
    """The `tiny` schedule as shipped: 2 rounds on 16 photos, seed 0 (about 40 s on one core)."""
    torch.set_num_threads(1)
    cfg = resolve_config("tiny", None, {"images": str(images16), "seed": 0, "progress": False})
    return evolve(tmp_path_factory.mktemp("runs") / "tiny", cfg)


def quick_config(images, **overrides):
    values = {"images": str(images), "rounds": 1, "epochs_desc": 2, "epochs_det": 2, "validate": False,
              "progress": False, **overrides}
    return resolve_config("tiny", None, values)


def test_tiny_run_improves_held_out_matching(tiny_run):
    start, *rounds = sorted(tiny_run.validation, key=validation_position)
    assert start["task"] == "start" and [r["task"] for r in rounds] == ["r0_b", "r0_d", "r1_b", "r1_d"]
    final = rounds[-1]
    assert all(-1 <= r["desc_cos"] <= 1 for r in [start, *rounds])  # the collapse diagnostic is recorded
    # Held-out homography sequences (never trained on): the random start matches worse.
    assert final["mma3"] > start["mma3"] + 0.02
    assert final["ha_avg"] > start["ha_avg"]
    best = load_model(tiny_run.best)[1].meta
    assert best["validation"]["mma3"] == max(r["mma3"] for r in rounds)


def test_run_folder_records_everything(tiny_run, images16):
    root = tiny_run.folder
    state = json.loads((root / "state.json").read_text())
    assert state["done"] == ["start", "r0_a0", "r0_b", "r0_c", "r0_d", "r1_a", "r1_b", "r1_c", "r1_d"]
    cfg = load_run_config(root / "config.yaml")
    assert cfg.schedule == "tiny" and cfg.rounds == 2 and cfg.images == str(images16)
    epochs = json.loads((root / "history.json").read_text())["epochs"]
    assert [(e["task"], e["epoch"]) for e in epochs] == (
        [("r0_b", i) for i in range(4)] + [("r0_d", 0)] + [("r1_b", i) for i in range(4)] + [("r1_d", 0)])
    assert (root / "losses.csv").read_text().count("\n") == 11
    assert (root / "metrics.csv").read_text().count("\n") == 6
    assert (root / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "validation after r1_d" in (root / "train.log").read_text()
    for task in ("r0_b", "r0_d", "r1_b", "r1_d"):
        assert (root / "models" / f"{task}.pth").is_file()
    assert {p.name for p in (root / "labels").iterdir()} == {"r0_a0.npz", "r0_c.npz", "r1_a.npz", "r1_c.npz"}
    assert not (root / "checkpoints" / "resume.pt").exists()


def test_exported_models_load_and_run_in_extract(tiny_run, images8, tmp_path):
    _, info = load_model(tiny_run.last)
    assert info.meta["task"] == "r1_d" and info.meta["schedule"] == "tiny"
    out = tmp_path / "features.h5"
    result = CliRunner().invoke(sekd, ["extract", str(images8), "-o", str(out), "--weights", str(tiny_run.best),
                                       "--max-keypoints", "50", "--precision", "fp32", "--device", "cpu",
                                       "--num-threads", "1", "--no-progress"])
    assert result.exit_code == 0, result.output
    with h5py.File(out) as f:
        assert len(f.keys()) == 8
        group = f[min(f.keys())]
        assert 0 < group["keypoints"].shape[0] <= 50 and group["descriptors"].shape[0] == 128


@pytest.fixture(scope="module")
def quick_run(images8, tmp_path_factory):
    """An uninterrupted `quick_config` run: round 0 with random keypoints, a0, b (2 epochs), c, d (2 epochs)."""
    torch.set_num_threads(1)
    return evolve(tmp_path_factory.mktemp("quick") / "whole", quick_config(images8))


def test_resume_after_every_epoch_equals_uninterrupted(quick_run, images8, tmp_path, monkeypatch):
    torch.set_num_threads(1)
    cfg, reference = quick_config(images8), quick_run

    original = RunFolder.save_epoch

    def crash_after_saving(self, *args, **kwargs):
        original(self, *args, **kwargs)
        raise KeyboardInterrupt  # as if Ctrl-C arrived right after the checkpoint

    monkeypatch.setattr(RunFolder, "save_epoch", crash_after_saving)
    with pytest.raises(KeyboardInterrupt):
        evolve(tmp_path / "resumed", cfg)
    interruptions = 1
    while True:
        try:
            resumed = evolve(tmp_path / "resumed", None, resume=True)
            break
        except KeyboardInterrupt:
            interruptions += 1
    assert interruptions == 4  # once after every epoch (the last one's save happens before 'done')
    a = torch.load(reference.last, weights_only=True)["state_dict"]
    b = torch.load(resumed.last, weights_only=True)["state_dict"]
    assert a.keys() == b.keys()
    for key in a:  # same process, same threads: the resumed run is bitwise identical
        assert torch.equal(a[key], b[key]), key
    losses = [(run / "losses.csv").read_text() for run in (reference.folder, tmp_path / "resumed")]
    assert losses[0] == losses[1]


def test_labelling_interrupted_after_every_image_resumes_to_the_same_run(quick_run, images8, tmp_path, monkeypatch):
    torch.set_num_threads(1)
    original = labels_module.save_part

    def crash_after_saving(*args, **kwargs):
        original(*args, **kwargs)
        raise KeyboardInterrupt  # as if Ctrl-C arrived right after an image's labels were saved

    monkeypatch.setattr(labels_module, "PARTS_EVERY_SECONDS", 0.0)  # save after every image
    monkeypatch.setattr(labels_module, "save_part", crash_after_saving)
    interruptions, resume = 0, False
    while interruptions < 50:  # bounded: a resume that relabelled saved images would crash forever
        try:
            resumed = evolve(tmp_path / "resumed", None if resume else quick_config(images8), resume=resume)
            break
        except KeyboardInterrupt:
            interruptions, resume = interruptions + 1, True
    records = json.loads((quick_run.folder / "history.json").read_text())["labels"]
    assert [r["task"] for r in records] == ["r0_a0", "r0_c"]
    assert interruptions == sum(r["images"] for r in records)  # once per labelled image, each labelled once
    assert {p.name for p in (resumed.folder / "labels").iterdir()} == {"r0_a0.npz", "r0_c.npz"}  # parts deleted
    for task in ("r0_a0", "r0_c"):  # same process, same threads: bitwise the uninterrupted labels and model
        with np.load(quick_run.folder / "labels" / f"{task}.npz") as a, np.load(resumed.folder / "labels" / f"{task}.npz") as b:
            assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files), task
    a = torch.load(quick_run.last, weights_only=True)["state_dict"]
    b = torch.load(resumed.last, weights_only=True)["state_dict"]
    assert all(torch.equal(a[key], b[key]) for key in a)
    assert "labelled before the interruption" in (resumed.folder / "train.log").read_text()


def test_resume_and_new_run_errors(images8, tmp_path):
    with pytest.raises(SekdError, match="no run to resume"):
        evolve(tmp_path / "nothing", None, resume=True)
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "state.json").write_text("{}")
    with pytest.raises(SekdError, match="already holds a run"):
        evolve(folder, quick_config(images8))
    with pytest.raises(SekdError, match="training image folder not found"):
        evolve(tmp_path / "new", quick_config(tmp_path / "missing"))


def test_train_one_step_from_a_checkpoint(tiny_run, images8, tmp_path):
    torch.set_num_threads(1)
    cfg = quick_config(images8, init_weights=str(tiny_run.last), epochs_desc=1)
    result = train_one_step(tmp_path / "step", cfg, step="desc", keypoints="detector", round_index=3)
    state = json.loads((tmp_path / "step" / "state.json").read_text())
    assert state["done"] == ["r3_a", "r3_b"]
    start = load_model(tiny_run.last)[0].state_dict()
    trained = load_model(result.last)[0].state_dict()
    assert not torch.equal(start["descriptor.convb.2.weight"], trained["descriptor.convb.2.weight"])


def lr_path(optimizer, scheduler, losses) -> list[float]:
    """The learning rate of each epoch while the scheduler is stepped with ``losses``, one per epoch."""
    path = []
    for loss in losses:
        path.append(optimizer.param_groups[0]["lr"])
        optimizer.step()  # no gradients: changes nothing, keeps torch's call-order check quiet
        scheduler.step(loss)
    return path


def test_halfway_schedule_ignores_the_losses_and_resumes_on_its_path():
    net = torch.nn.Linear(2, 1)
    def fresh():
        optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
        return optimizer, HalfwayDrop(optimizer, epochs=8, factor=0.1)
    path = lr_path(*fresh(), [5.0, 4.0, 3.0, 2.0, 1.0, 9.0, 9.0, 9.0])  # falling, then a plateau: neither matters
    assert path == pytest.approx([1e-3] * 4 + [1e-4] * 4)
    # resumed from the state saved after three epochs, it continues on the same path
    saved_optimizer, saved = fresh()
    lr_path(saved_optimizer, saved, [0.0] * 3)
    optimizer, scheduler = fresh()
    optimizer.load_state_dict(saved_optimizer.state_dict())
    scheduler.load_state_dict(saved.state_dict())
    assert lr_path(optimizer, scheduler, [0.0, 0.0]) == pytest.approx([1e-3, 1e-4])


@pytest.mark.parametrize("epochs,full", [(1, 1), (2, 1), (3, 2), (8, 4)])
def test_halfway_schedule_rounds_the_half_up(epochs, full):
    """A one-epoch step must run at lr (rounding down gave it plateau_factor * lr throughout)."""
    cfg = TrainConfig(lr=1e-3, lr_schedule="halfway", plateau_factor=0.1)
    optimizer, scheduler = _optimiser(torch.nn.Linear(2, 1), cfg, epochs)
    path = lr_path(optimizer, scheduler, [1.0] * epochs)
    assert path == pytest.approx([1e-3] * full + [1e-4] * (epochs - full))


def test_halfway_schedule_in_a_run(images8, tmp_path):
    torch.set_num_threads(1)
    cfg = quick_config(images8, epochs_desc=4, epochs_det=2, lr_schedule="halfway")
    run = evolve(tmp_path / "run", cfg)
    history = json.loads((run.folder / "history.json").read_text())["epochs"]
    rates = {(e["task"], e["epoch"]): e["lr"] for e in history}
    assert [rates[("r0_b", e)] for e in range(4)] == pytest.approx([1e-3, 1e-3, 1e-4, 1e-4])
    assert [rates[("r0_d", e)] for e in range(2)] == pytest.approx([1e-3, 1e-4])
    result = CliRunner().invoke(sekd, ["evolve", "--images", str(images8), "--out", str(tmp_path / "bad"),
                                       "--set", "lr_schedule=cosine"])
    assert result.exit_code == 1 and "lr_schedule" in result.output
    assert result.output.strip().count("\n") == 0, result.output


HEAP_PROBE = """
import sys
import numpy as np
from sekd_sfm.bench.scale.measure import proc_status
from sekd_sfm.runtime import allocator_tuned, tune_allocator

def kept_mb():
    \"\"\"MB a touched and freed 256 MB array leaves in the process (resident).\"\"\"
    block = np.ones(256 << 20, dtype=np.uint8)
    alive = proc_status()["VmRSS"]
    del block
    return 256 - ((alive - proc_status()["VmRSS"]) >> 20)

if sys.argv[1] == "caller":  # the caller had tuned the allocator: the block leaves it tuned
    tune_allocator()
with allocator_tuned() as tuned:
    inside = kept_mb()
print(tuned, inside, kept_mb())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator (mallopt) and /proc")
@pytest.mark.parametrize("mode,kept_after", [("plain", False), ("caller", True)])
def test_allocator_tuned_keeps_freed_memory_only_inside_the_block(mode, kept_after):
    done = subprocess.run([sys.executable, "-c", HEAP_PROBE, mode], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "OMP_NUM_THREADS": "1"}, check=False)
    assert done.returncode == 0, done.stderr
    tuned, inside, after = done.stdout.split()
    assert tuned == "True" and int(inside) >= 200  # freed, yet still in the heap for the next training step
    assert (int(after) >= 200) is kept_after  # given back to the OS unless the caller had tuned it


def test_training_runs_with_the_allocator_tuned_and_restores_it(images8, tmp_path, monkeypatch):
    """CPU training keeps freed buffers in the heap (no fresh zeroed pages every step), then leaves glibc as it was."""
    untune_allocator()  # earlier tests' networks may have tuned this process
    seen = []
    original = Runner.run

    def run_and_look(self):
        seen.append(tuning_requested())
        return original(self)

    monkeypatch.setattr(Runner, "run", run_and_look)
    torch.set_num_threads(1)
    evolve(tmp_path / "run", quick_config(images8, epochs_desc=1, epochs_det=1))
    assert seen == [True] and not tuning_requested()


def test_every_run_leaves_its_process_group_even_when_interrupted(images8, tmp_path, monkeypatch):
    """torchrun processes leave the group at the end of each run (a library caller may start another)."""
    from sekd_sfm.train import evolve as evolve_module

    left = []
    monkeypatch.setattr(evolve_module, "teardown", lambda: left.append(True))
    monkeypatch.setattr(Runner, "run", lambda self: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(KeyboardInterrupt):
        evolve(tmp_path / "run", quick_config(images8, validate=False))
    assert left == [True]


@pytest.mark.parametrize("args,message", [
    (["evolve", "--images", "/no/such/folder", "--out", "{tmp}/r", "--schedule", "tiny"], "image folder not found"),
    (["evolve", "--images", "{tmp}", "--out", "{tmp}/r", "--set", "bogus=1"], "unknown config key"),
    (["evolve", "--out", "{tmp}/none", "--resume"], "no run to resume"),
    (["train", "--out", "{tmp}/r", "--weights", "/no/such.pth", "--images", "{tmp}"], "starting weights not found"),
])
def test_cli_user_errors_are_one_line(args, message, tmp_path):
    result = CliRunner().invoke(sekd, [a.format(tmp=tmp_path) for a in args])
    assert result.exit_code == 1
    assert message in result.output and result.output.strip().count("\n") == 0, result.output


def test_cli_train_writes_models(images8, tmp_path):
    out = tmp_path / "run"
    result = CliRunner().invoke(sekd, ["train", "--images", str(images8), "--out", str(out), "--schedule", "tiny",
                                       "--step", "det", "--keypoints", "reliability", "--set", "epochs_det=1",
                                       "--set", "validate=false", "--no-progress", "--seed", "3"])
    assert result.exit_code == 0, result.output
    assert f"best model: {out / 'best.pth'}" in result.output
    assert load_model(out / "last.pth")[1].meta["step"] == "d"
    assert load_run_config(out / "config.yaml").seed == 3


def test_two_process_data_parallel_run(images8, tmp_path):
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "SEKD_SHARED": str(SHARED)}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "sekd_sfm.cli.main", "evolve", "--images", str(images8), "--out", str(out), "--schedule", "tiny",
           "--no-progress", "--num-threads", "1", "--set", "rounds=1", "--set", "epochs_desc=1",
           "--set", "val_sets=[data/homography/hpatches/*]"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = (out / "train.log").read_text()
    assert "2 process(es)" in log
    assert log.count("weights identical on all 2 processes") == 2  # after (b) and after (d)
    with np.load(out / "labels" / "r0_c.npz") as z:
        assert sorted(z["indices"].tolist()) == list(range(8))  # each process labelled half, all gathered
    assert not list((out / "labels").glob("*.parts"))  # both processes' chunk files deleted with the step done
    assert load_model(out / "best.pth")[1].meta["task"] in ("r0_b", "r0_d")  # both steps validate


@pytest.mark.parametrize("variant", [
    {"desc_loss": "margin", "margin_normalise": "nonzero", "det_preserve_on": "prob", "rep_loss": "paper",
     "lambda_keep": 1e-3, "label_warp": "inverse", "jitter_target": False, "isotropic_scale": True},
    {"no_desc_rep": True, "no_desc_dis": False, "no_det_rep": True, "no_affine": True, "rel_threshold": 0.5},
    {"no_desc_dis": True, "round0_random": False, "save_maps": True, "keep_epoch_checkpoints": False},
])
def test_paper_variants_and_ablations_run(variant, images8, tmp_path):
    torch.set_num_threads(1)
    result = evolve(tmp_path / "run", quick_config(images8, epochs_desc=1, epochs_det=1, **variant))
    _, info = load_model(result.last)
    assert info.meta["config"]["rep_loss"] == variant.get("rep_loss", "weighted")
    losses = json.loads((tmp_path / "run" / "history.json").read_text())["epochs"]
    assert losses and all(np.isfinite(e["total"]) for e in losses)
    with np.load(tmp_path / "run" / "labels" / "r0_c.npz") as z:
        assert z["counts"].sum() > 0 and (f"map_{z['indices'][0]}" in z) == variant.get("save_maps", False)


@pytest.mark.parametrize(("setting", "value", "reused"), [("spread_weight", 1.0, ["r0_c", "r0_d", "r1_a"]),
                                                           ("perspective", 0.1, ["r0_c"]),
                                                           ("train_precision", "bf16", ["r0_c"])])
def test_fork_equals_a_run_started_with_the_changed_setting(images8, tmp_path, setting, value, reused):
    from sekd_sfm.train.fork import fork_run

    torch.set_num_threads(1)
    cfg = quick_config(images8, rounds=2, round0_random=False, epochs_desc=1, epochs_det=1)
    evolve(tmp_path / "source", cfg)
    reference = evolve(tmp_path / "reference", quick_config(images8, rounds=2, round0_random=False, epochs_desc=1,
                                                             epochs_det=1, **{setting: value}))
    fork_run(tmp_path / "source", tmp_path / "fork", {setting: value})
    state = json.loads((tmp_path / "fork" / "state.json").read_text())
    assert state["done"] == reused and state["forked_from"]["changed"] == [setting]
    assert state["forked_from"]["run"] == "../source"  # relative: the record holds in another clone
    assert "forked from" in (tmp_path / "fork" / "train.log").read_text().splitlines()[-1]
    forked = evolve(tmp_path / "fork", None, resume=True)
    a = torch.load(reference.last, weights_only=True)["state_dict"]
    b = torch.load(forked.last, weights_only=True)["state_dict"]
    for key in a:  # reusing round 0 and the (a) labels changes nothing
        assert torch.equal(a[key], b[key]), key
    source = torch.load(tmp_path / "source" / "last.pth", weights_only=True)["state_dict"]
    assert any(not torch.equal(source[key], b[key]) for key in source)  # the setting did change the training
    assert all(t.is_contiguous() for t in b.values())  # bf16 steps train channels-last, and hand back contiguous
    assert getattr(load_run_config(tmp_path / "fork" / "config.yaml"), setting) == value


def test_training_autocast_dtype():
    from sekd_sfm.runtime import cpu_has_fast_bf16
    from sekd_sfm.train.steps import autocast_dtype

    cpu = torch.device("cpu")
    assert autocast_dtype("fp32", cpu) is None and autocast_dtype("bf16", cpu) is torch.bfloat16
    assert autocast_dtype("auto", cpu) is (torch.bfloat16 if cpu_has_fast_bf16() else None)
    with pytest.raises(SekdError, match="train_precision"):
        resolve_config("tiny", None, {"train_precision": "fp16"})


def test_fork_refuses_settings_of_steps_already_run(images8, tmp_path):
    from sekd_sfm.train.fork import fork_run

    torch.set_num_threads(1)
    evolve(tmp_path / "source", quick_config(images8, epochs_desc=1, epochs_det=1))
    with pytest.raises(SekdError, match="lr change steps the source already ran"):
        fork_run(tmp_path / "source", tmp_path / "fork", {"lr": 1e-4})
    assert not (tmp_path / "fork" / "state.json").exists()
    with pytest.raises(SekdError, match="already holds a run"):
        fork_run(tmp_path / "source", tmp_path / "source", {"spread_weight": 1.0})
    result = CliRunner().invoke(sekd, ["evolve", "--fork", str(tmp_path / "source"), "--out", str(tmp_path / "f2"),
                                       "--resume"])
    assert result.exit_code != 0 and "--fork takes the source run's config" in result.output


def test_fork_reuses_the_finished_tasks_before_the_first_changed_step():
    from sekd_sfm.train.evolve import evolve_tasks
    from sekd_sfm.train.fork import reusable_tasks

    tasks = evolve_tasks(resolve_config("cpu", None, {"rounds": 3}))
    done = ["start", "r0_c", "r0_d", "r1_a", "r1_b", "r1_c"]
    assert [t.id for t in reusable_tasks(tasks, done, ["spread_weight", "rounds"])] == ["r0_c", "r0_d", "r1_a"]
    assert [t.id for t in reusable_tasks(tasks, done, ["rounds", "num_threads"])] == done[1:]
    assert [t.id for t in reusable_tasks(tasks, done, ["perspective"])] == ["r0_c"]  # (d) reads it too
    assert [t.id for t in reusable_tasks(tasks, done, ["perspective", "spread_weight"])] == ["r0_c"]
    assert [t.id for t in reusable_tasks(tasks, done, ["train_precision"])] == ["r0_c"]
    with pytest.raises(SekdError, match="no_affine"):
        reusable_tasks(tasks, done, ["no_affine", "alpha"])
