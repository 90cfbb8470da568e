"""Hardening (#16): one `Error:` line for OS failures and bad input, the pixel cap, option ranges,
validated training settings, the run-folder lock and the resume check of the image list."""
from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.failures import explain
from sekd_sfm.files import features as ff
from sekd_sfm.files import partstore
from sekd_sfm.files.images import (
    ImageReadError,
    image_size,
    load_scaled,
    reduction_factor,
    to_original_pixels,
)
from sekd_sfm.runtime import resolve_device, set_num_threads


def textured(seed: int, shape=(120, 160)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = (rng.random((shape[0] // 8, shape[1] // 8)) * 255).astype(np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, shape[::-1], interpolation=cv2.INTER_CUBIC), (3, 3), 0)


def write_images(folder: Path, count: int = 3, shape=(120, 160)) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        cv2.imwrite(str(folder / f"{i}.png"), textured(i, shape))
    return folder


def run(*args, env=None):
    return CliRunner().invoke(sekd, ["-q", *map(str, args)], env=env)


def assert_one_error(result, *fragments: str) -> str:
    """Exit code 1, exactly one `Error:` line (containing ``fragments``), no traceback."""
    output = result.output
    errors = [line for line in output.splitlines() if line.startswith("Error:")]
    assert result.exit_code == 1, output
    assert len(errors) == 1, output
    assert "Traceback" not in output and isinstance(result.exception, SystemExit), (output, result.exception)
    for fragment in fragments:
        assert fragment in errors[0], errors[0]
    return errors[0]


def extract_args(images: Path, output: Path, *extra) -> list:
    return ["extract", images, "-o", output, "--feature", "sift", "--max-keypoints", 100, "--no-progress", *extra]


# --- #16.2: OS errors and bad input end as one line ------------------------------------------------


def test_disk_full_simulated_keeps_finished_images_and_resumes(tmp_path, monkeypatch):
    images, out = write_images(tmp_path / "img", 4), tmp_path / "f.h5"
    real_save, saved = partstore.PartStore.save, []

    def save_until_full(self, key, arrays):
        if len(saved) == 2:
            raise OSError(errno.ENOSPC, "No space left on device", f"{out}.parts/{key}.npz")
        saved.append(key)
        return real_save(self, key, arrays)

    monkeypatch.setattr(partstore.PartStore, "save", save_until_full)
    line = assert_one_error(run(*extract_args(images, out)), "disk full", "MB free there",
                            "run the same command again to resume")
    assert str(tmp_path) in line
    monkeypatch.setattr(partstore.PartStore, "save", real_save)
    result = run(*extract_args(images, out))
    assert result.exit_code == 0, result.output
    assert ff.list_keys(out) == ["0.png", "1.png", "2.png", "3.png"]
    clean = tmp_path / "clean.h5"
    assert run(*extract_args(images, clean)).exit_code == 0
    for key in ff.list_keys(clean):  # the two images saved before the failure are the same as in a clean run
        np.testing.assert_array_equal(ff.read_features(out, key)["keypoints"], ff.read_features(clean, key)["keypoints"])


@pytest.fixture
def small_tmpfs(tmp_path):
    """A 1 MB tmpfs (needs root and mount rights; skipped otherwise)."""
    mount = tmp_path / "tmpfs"
    mount.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)], capture_output=True, text=True,
                          check=False)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def test_disk_full_on_a_real_small_tmpfs(tmp_path, small_tmpfs):
    images = tmp_path / "img"
    images.mkdir()
    for i in range(8):  # noise: SIFT finds its 300 keypoints, 150 KB per image
        rng = np.random.default_rng(i)
        cv2.imwrite(str(images / f"{i}.png"), cv2.GaussianBlur((rng.random((240, 320)) * 255).astype(np.uint8), (0, 0), 2))
    out = small_tmpfs / "f.h5"
    args = ["extract", images, "-o", out, "--feature", "sift", "--max-keypoints", 300, "--no-progress"]
    assert_one_error(run(*args), "disk full", str(out), "0 MB free there", "run the same command again")
    subprocess.run(["mount", "-o", "remount,size=20m", str(small_tmpfs)], check=True)
    result = run(*args)
    assert result.exit_code == 0, result.output
    assert len(ff.list_keys(out)) == 8


def test_output_under_a_file_is_one_line(tmp_path):
    images = write_images(tmp_path / "img", 1)
    (tmp_path / "afile").write_text("not a folder")
    line = assert_one_error(run(*extract_args(images, tmp_path / "afile" / "f.h5")))
    assert "afile" in line
    assert (tmp_path / "afile").read_text() == "not a folder"


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA GPU is present")
def test_device_cuda_without_gpu(tmp_path):
    images = write_images(tmp_path / "img", 1)
    line = assert_one_error(run("extract", images, "-o", tmp_path / "f.h5", "--device", "cuda", "--no-progress"))
    assert "--device cuda" in line and "--device cpu" in line
    with pytest.raises(SekdError, match="--device cuda"):
        resolve_device("cuda")


@pytest.mark.parametrize("value", ["-1", "0"])
def test_num_threads_range(tmp_path, value):
    images = write_images(tmp_path / "img", 1)
    for args in (extract_args(images, tmp_path / "f.h5", "--num-threads", value),
                 ["match", tmp_path / "f.h5", tmp_path / "p.txt", "--num-threads", value]):
        result = run(*args)
        assert result.exit_code == 2 and "Invalid value for '--num-threads'" in result.output, result.output
    with pytest.raises(SekdError, match="--num-threads"):
        set_num_threads(-1)


@pytest.mark.parametrize("value", ["5", "0", "1", "-0.1"])
def test_threshold_must_be_a_probability(tmp_path, value):
    images = write_images(tmp_path / "img", 1)
    result = run("extract", images, "-o", tmp_path / "f.h5", "--threshold", value)
    assert result.exit_code == 2 and "Invalid value for '--threshold'" in result.output, result.output
    assert not (tmp_path / "f.h5").exists()


def test_match_features_without_descriptors(tmp_path):
    images = write_images(tmp_path / "img", 2)
    features, pairs = tmp_path / "f.h5", tmp_path / "pairs.txt"
    assert run(*extract_args(images, features)).exit_code == 0
    with h5py.File(features, "a") as f:
        del f["0.png"]["descriptors"]
    assert run("pairs", features, "-o", pairs).exit_code == 0
    line = assert_one_error(run("match", features, pairs, "-o", tmp_path / "m.h5", "--no-progress"))
    assert str(features) in line and "descriptors" in line


@pytest.mark.parametrize("feature", ["disk", "aliked", "xfeat"])
def test_bad_peer_checkpoint(tmp_path, feature):
    images = write_images(tmp_path / "img", 1)
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"PK\x03\x04 not really a zip")
    line = assert_one_error(run("extract", images, "-o", tmp_path / "f.h5", "--feature", feature,
                                "--weights", garbage, "--no-progress"))
    assert str(garbage) in line and "checkpoint" in line
    wrong = tmp_path / "wrong.pth"  # a valid file of tensors that is not this model
    torch.save({"extractor": {"x": torch.zeros(1)}, "net": torch.zeros(2)}, wrong)
    line = assert_one_error(run("extract", images, "-o", tmp_path / "g.h5", "--feature", feature,
                                "--weights", wrong, "--no-progress"))
    assert str(wrong) in line and feature in line.lower()


def test_unexpected_error_is_one_line_unless_sekd_debug(tmp_path, monkeypatch):
    import sekd_sfm.stages.extract as extract_module

    def broken(*args, **kwargs):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(extract_module, "list_images", broken)
    images = write_images(tmp_path / "img", 1)
    line = assert_one_error(run(*extract_args(images, tmp_path / "f.h5")), "ZeroDivisionError", "SEKD_DEBUG=1")
    assert "a bug" in line
    result = run(*extract_args(images, tmp_path / "f.h5"), env={"SEKD_DEBUG": "1"})
    assert isinstance(result.exception, ZeroDivisionError)


def test_permission_denied_names_the_path(tmp_path, monkeypatch):
    import sekd_sfm.stages.extract as extract_module

    target = tmp_path / "locked" / "f.h5"

    def denied(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(target))

    monkeypatch.setattr(extract_module, "list_images", denied)
    images = write_images(tmp_path / "img", 1)
    assert_one_error(run(*extract_args(images, target)), str(target), "permission denied")


@pytest.mark.parametrize("code, fragment", [
    (errno.EROFS, "read-only"), (errno.EIO, "input/output error"), (errno.ENOENT, "no such file"),
    (errno.EISDIR, "is a folder"), (errno.EMFILE, "ulimit -n"), (errno.EPERM, "permission denied"),
    (errno.EDQUOT, "disk full"),
])
def test_explain_os_errors(tmp_path, code, fragment):
    line = explain(OSError(code, os.strerror(code), str(tmp_path / "x.h5")))
    assert fragment in line and str(tmp_path / "x.h5") in line and "\n" not in line


def test_explain_not_a_directory_names_the_file_in_the_way(tmp_path):
    (tmp_path / "afile").write_text("")
    line = explain(NotADirectoryError(errno.ENOTDIR, "Not a directory", str(tmp_path / "afile" / "sub" / "f.h5")))
    assert f"{tmp_path / 'afile'} is a file, not a folder" in line


def test_explain_memory_and_hdf5_errors(tmp_path):
    assert "out of memory" in explain(MemoryError())
    assert "out of memory" in explain(RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried"))
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"garbage" * 10)
    try:
        h5py.File(bad, "r")
    except OSError as exc:
        line = explain(exc, inputs=["match", str(bad), "pairs.txt"])
    assert str(bad) in line and "HDF5" in line


# --- #16.3: the pixel cap ------------------------------------------------------------------------


def test_image_size_from_headers(tmp_path):
    image = np.zeros((37, 53, 3), np.uint8)
    for ext in (".png", ".jpg", ".tif", ".bmp", ".ppm", ".pgm"):
        cv2.imwrite(str(tmp_path / f"x{ext}"), image[..., 0] if ext == ".pgm" else image)
        assert image_size(tmp_path / f"x{ext}") == (53, 37), ext
    junk = {"junk.jpg": b"\xff\xd8\xff\xe0\x00", "empty.png": b"", "zero-length.jpg": b"\xff\xd8\xff\xe0\x00\x00",
            "no-markers.jpg": b"\xff\xd8" + bytes(1_000_000), "sof.jpg": b"\xff\xd8\xff\xc0\x00\x11\x08\x01\x00\x02\x00"}
    for name, data in junk.items():
        (tmp_path / name).write_bytes(data)
    assert [image_size(tmp_path / name) for name in junk] == [None, None, None, None, (512, 256)]


def test_reduction_factor():
    assert reduction_factor(12000, 9000, 200_000_000) == 1
    assert reduction_factor(12000, 9000, None) == 1
    assert reduction_factor(12000, 9000, 100_000_000) == 2
    assert reduction_factor(12000, 9000, 10_000_000) == 4
    assert reduction_factor(12000, 9000, 2_000_000) == 8
    with pytest.raises(ImageReadError, match="more than 64 times"):
        reduction_factor(12000, 9000, 1_000_000)


@pytest.mark.parametrize("ext, tolerance", [(".jpg", 0.05), (".png", 0.25)])
@pytest.mark.parametrize("factor", [2, 4, 8])
def test_reduced_decode_maps_back_to_original_pixels(tmp_path, ext, tolerance, factor):
    """A disk centred at (600, 400) in a 1003 x 803 image: its centroid in the reduced image maps back there.

    JPEG is reduced by libjpeg (scale = factor exactly), PNG by OpenCV resizing to floor(W / f)
    (scale = size ratio); the wrong convention is off by 0.6 px or more.
    """
    image = np.zeros((803, 1003), np.uint8)
    cv2.circle(image, (600, 400), 40, 255, -1)
    cv2.imwrite(str(tmp_path / f"d{ext}"), image, [cv2.IMWRITE_JPEG_QUALITY, 100])
    max_pixels = (1003 // factor) * (803 // factor)
    (height, width), small, sx, sy = load_scaled(tmp_path / f"d{ext}", None, True, max_pixels)
    assert (height, width) == (803, 1003) and small.shape[0] <= 803 // factor + 1
    weights = small.astype(np.float64) / small.sum()
    centroid = np.array([[(weights.sum(0) * np.arange(small.shape[1])).sum(),
                          (weights.sum(1) * np.arange(small.shape[0])).sum()]], np.float32)
    np.testing.assert_allclose(to_original_pixels(centroid, sx, sy)[0], [600, 400], atol=tolerance)


def test_reduced_decode_then_resize_max_composes(tmp_path):
    image = np.zeros((803, 1003), np.uint8)
    cv2.circle(image, (600, 400), 40, 255, -1)
    cv2.imwrite(str(tmp_path / "d.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 100])
    (height, width), small, sx, _ = load_scaled(tmp_path / "d.jpg", 100, True, 300_000)  # /2 decode, then 100 px
    assert max(small.shape) == 100 and (height, width) == (803, 1003)
    assert sx == pytest.approx(1003 / small.shape[1], rel=0.01)
    # Under the cap nothing changes: the same pixels as read_image + resize_max_side.
    (_, _), full, sx1, sy1 = load_scaled(tmp_path / "d.jpg", None, True, 10_000_000)
    assert full.shape == (803, 1003) and sx1 == sy1 == 1.0


def _big_png(path: Path, width: int, height: int) -> Path:
    """A mostly constant PNG (compresses to ~100 KB) with a few corners for SIFT."""
    image = np.full((height, width), 90, np.uint8)
    for i in range(12):
        x, y = (i * 977) % (width - 800) + 100, (i * 631) % (height - 800) + 100
        cv2.rectangle(image, (x, y), (x + 500, y + 350), 30 + 17 * i, -1)
    cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return path


@pytest.fixture(scope="module")
def big_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("big")
    _big_png(folder / "big.png", 8000, 6000)  # 48 MP
    cv2.imwrite(str(folder / "small.png"), textured(0))
    return folder


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="peak memory is read from /proc (Linux)")
def test_huge_image_is_decoded_reduced_with_exact_keypoints_and_bounded_memory(big_folder, tmp_path):
    """48 MP with --max-pixels 1e6: decoded at 1/8 (1000 x 750); peak memory stays far below a full-size run."""
    out = tmp_path / "f.h5"
    script = (
        "import sys; from sekd_sfm.cli.main import sekd\n"
        "try:\n    sekd(sys.argv[1:], prog_name='sekd')\n"
        "except SystemExit as e:\n    code = e.code\n"
        # VmHWM, not ru_maxrss: Linux carries the parent's peak RSS over fork/exec into the child's
        # ru_maxrss, so a large pytest process (> 1 GB late in the suite) would be measured instead.
        "print('PEAK_MB', int(next(l for l in open('/proc/self/status') if l.startswith('VmHWM:')).split()[1]) / 1024)\n"
        "sys.exit(code)\n")
    done = subprocess.run([sys.executable, "-c", script, "-q", "extract", str(big_folder), "-o", str(out),
                           "--feature", "sift", "--max-keypoints", "200", "--max-pixels", "1000000", "--no-progress"],
                          capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, check=False)
    assert done.returncode == 0, done.stderr
    peak = float(done.stdout.split("PEAK_MB")[1])
    # The decode holds the 48 MB PNG once; SIFT at full size (2x upsampled float pyramid) would need > 3 GB.
    assert peak < 900, peak
    features = ff.read_features(out, "big.png")
    assert features["image_size"].tolist() == [8000, 6000]
    reduced = cv2.imread(str(big_folder / "big.png"), cv2.IMREAD_REDUCED_GRAYSCALE_8)
    assert reduced.shape == (750, 1000)
    from sekd_sfm.features.classic import OpenCVExtractor
    expected = OpenCVExtractor("sift", 200).extract(reduced)
    np.testing.assert_array_equal(features["keypoints"], to_original_pixels(expected["keypoints"], 8.0, 8.0))
    assert len(features["keypoints"]) > 10


def test_image_beyond_64x_the_cap_is_skipped_and_listed(big_folder, tmp_path):
    out = tmp_path / "f.h5"
    result = run(*extract_args(big_folder, out, "--max-pixels", 500_000))
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.output.splitlines() if "big.png" in line]
    assert len(warnings) == 1 and "64 times the pixel cap" in warnings[0] and "skipped" in warnings[0]
    assert ff.list_keys(out) == ["small.png"]
    assert json.loads(ff.read_attrs(out)["failed_images"]) == ["big.png"]


# --- #16.4: training settings, resume check, run-folder lock -------------------------------------


@pytest.fixture
def train_images(tmp_path):
    return write_images(tmp_path / "train", 4, shape=(96, 128))


def evolve_args(images: Path, out: Path, *settings: str) -> list:
    args = ["evolve", "--images", images, "--out", out, "--schedule", "tiny", "--no-progress", "--num-threads", 1]
    for setting in settings:
        args += ["--set", setting]
    return args


@pytest.mark.parametrize("setting, fragment", [
    ("lr=-1", "'lr' must be in (0, 10]"), ("lr=0", "'lr'"), ("lr=.nan", "'lr'"), ("lr=abc", "cannot use 'abc'"),
    ("epochs_desc=-3", "'epochs_desc' must be between 1"), ("epochs_det=0", "'epochs_det'"),
    ("rounds=0", "'rounds' must be between 1"), ("crop_height=1000000", "'crop_height' must be between 16 and 4096"),
    ("crop_height=256", "must be <= long_side (128)"), ("crop_width=66", "multiple of 4"),
    ("batch_size=0", "'batch_size'"), ("scale=[2, 1]", "'scale' must be a range"), ("scale=[0, 1]", "'scale' must lie"),
    ("val_threshold=2", "'val_threshold'"), ("plateau_factor=1.5", "'plateau_factor'"), ("det_threshold=-0.1", "'det_threshold'"),
    ("num_workers=-1", "'num_workers'"), ("label_chunk=0", "'label_chunk'"), ("bogus=1", "unknown config key"),
])
def test_invalid_training_settings_are_one_line(train_images, tmp_path, setting, fragment):
    out = tmp_path / "run"
    assert_one_error(run(*evolve_args(train_images, out, setting)), fragment)
    assert not (out / "state.json").exists()


def test_training_step_memory_is_checked_against_the_machine(train_images, tmp_path):
    from sekd_sfm.train.config import check_memory, resolve_config, step_memory

    tiny = resolve_config("tiny", None, {"images": str(train_images)})
    assert step_memory(tiny) < 2**30
    check_memory(tiny, available=16 * 2**30)
    with pytest.raises(SekdError, match=r"needs about .* GB .* this machine has 0.5 GB; lower crop_height"):
        check_memory(tiny, available=2**29)
    big = ("long_side=4096", "crop_height=4096", "crop_width=4096", "batch_size=64")
    assert_one_error(run(*evolve_args(train_images, tmp_path / "run", *big)), "needs about", "this machine has")


@pytest.fixture
def stopped_run(train_images, tmp_path, monkeypatch):
    """A run folder whose first task never ran: state.json written, training interrupted at once."""
    from sekd_sfm.train import evolve as evolve_module

    def interrupted(self):
        raise KeyboardInterrupt

    monkeypatch.setattr(evolve_module.Runner, "run", interrupted)
    out = tmp_path / "run"
    result = run(*evolve_args(train_images, out, "validate=false"))
    assert result.exit_code == 1 and "sekd evolve --resume" in result.output, result.output
    monkeypatch.setattr(evolve_module.Runner, "run", lambda self: None)
    return out


def test_resume_with_changed_images_is_refused(stopped_run, train_images):
    state = json.loads((stopped_run / "state.json").read_text())
    assert state["images"]["count"] == 4 and len(state["images"]["sha256"]) == 64
    assert run("evolve", "--resume", "--out", stopped_run, "--no-progress").exit_code == 0  # unchanged: resumes
    cv2.imwrite(str(train_images / "new.png"), textured(9, (96, 128)))
    line = assert_one_error(run("evolve", "--resume", "--out", stopped_run, "--no-progress"),
                            "training images changed", "4 images then, 5 now")
    assert str(train_images) in line
    (train_images / "new.png").unlink()
    cv2.imwrite(str(train_images / "0.png"), textured(7, (96, 128)))  # same name and count, other content
    assert_one_error(run("evolve", "--resume", "--out", stopped_run, "--no-progress"), "training images changed")
    assert json.loads((stopped_run / "state.json").read_text()) == state  # the run is untouched


def test_resume_of_a_run_without_an_image_record_records_it(stopped_run):
    state = json.loads((stopped_run / "state.json").read_text())
    recorded = state.pop("images")
    (stopped_run / "state.json").write_text(json.dumps(state))
    assert run("evolve", "--resume", "--out", stopped_run, "--no-progress").exit_code == 0
    assert json.loads((stopped_run / "state.json").read_text())["images"] == recorded


def test_second_run_on_a_locked_run_folder_is_refused(stopped_run):
    holder = subprocess.Popen(
        [sys.executable, "-c", ("import sys, time; from sekd_sfm.files.locking import exclusive_lock\n"
                                f"with exclusive_lock({str(stopped_run)!r}, what='run folder'):\n"
                                "    print('locked', flush=True); time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = (stopped_run / "state.json").read_bytes()
        for args in (["evolve", "--resume", "--out", stopped_run, "--no-progress"],
                     ["train", "--resume", "--out", stopped_run, "--no-progress"]):
            assert_one_error(run(*args), "in use by another sekd process", f"PID {holder.pid}")
        assert (stopped_run / "state.json").read_bytes() == before
    finally:
        holder.kill()
        holder.wait()
    assert run("evolve", "--resume", "--out", stopped_run, "--no-progress").exit_code == 0  # a dead holder's lock is free


def test_signals_during_the_interrupt_cleanup_are_ignored():
    """After the first SIGTERM, a repeated SIGTERM or a Ctrl-C during cleanup must not kill the process
    by signal (exit -15/-2 instead of the one Error line and code 1); the next command re-arms them."""
    script = (
        "import os, signal, sys, time\n"
        "from sekd_sfm.runtime import stop_cleanly_on_sigterm\n"
        "for attempt in range(2):  # the second one: as a second command in the same process\n"
        "    stop_cleanly_on_sigterm()\n"
        "    try:\n        os.kill(os.getpid(), signal.SIGTERM); time.sleep(10); sys.exit(3)\n"
        "    except KeyboardInterrupt:\n"
        "        os.kill(os.getpid(), signal.SIGTERM); os.kill(os.getpid(), signal.SIGINT); time.sleep(0.2)\n"
        "        print('saved', attempt, file=sys.stderr)\n"
        "sys.exit(1)\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                          env={**os.environ, "OMP_NUM_THREADS": "1"}, check=False)
    assert done.returncode == 1 and done.stderr.split() == ["saved", "0", "saved", "1"], (done.returncode, done.stderr)


def test_interrupt_inside_exec_of_source_text_still_exits_with_code_1(tmp_path):
    """CPython marks a KeyboardInterrupt escaping ``exec()`` of source text (dataclasses and
    namedtuple build methods that way while a module imports) as unhandled even when caught, and
    ``python -m`` then kills itself by SIGINT (-2) after our Error line; the entry point clears the mark."""
    (tmp_path / "interrupted_command.py").write_text(
        "import sys\n"
        "import sekd_sfm.cli.main as entry\n"
        "from sekd_sfm.runtime import stop_cleanly_on_sigterm\n"
        "def command(**kw):\n"
        "    stop_cleanly_on_sigterm()\n"
        "    try:\n"
        "        exec('import os, signal\\nos.kill(os.getpid(), signal.SIGTERM)\\n', {})\n"
        "    except KeyboardInterrupt:\n"
        "        print('saved', file=sys.stderr)\n"
        "        sys.exit(1)\n"
        "entry.sekd = command\n"
        "entry.main()\n")
    done = subprocess.run([sys.executable, "-m", "interrupted_command"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=60, env={**os.environ, "OMP_NUM_THREADS": "1"}, check=False)
    assert (done.returncode, done.stderr.split()) == (1, ["saved"]), (done.returncode, done.stderr)


def test_concurrent_evolve_on_one_folder_is_refused(train_images, tmp_path):
    """A real `sekd evolve` runs; a second one on its folder is refused naming it; the first stops cleanly."""
    import signal
    import time

    out = tmp_path / "run"
    first = subprocess.Popen([sys.executable, "-m", "sekd_sfm.cli.main", *map(str, evolve_args(train_images, out,
                                                                                               "validate=false"))],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        deadline = time.monotonic() + 60
        while not ((out / "state.json").is_file() and (out / ".lock").is_file()
                   and (out / ".lock").read_text().strip() == str(first.pid)):
            assert first.poll() is None and time.monotonic() < deadline, first.communicate()
            time.sleep(0.2)
        assert_one_error(run("evolve", "--resume", "--out", out, "--no-progress"), "in use by another sekd process",
                         f"PID {first.pid}")
        assert_one_error(run(*evolve_args(train_images, out)), "in use by another sekd process")
    finally:
        first.send_signal(signal.SIGTERM)  # stops as on Ctrl-C: saves, says how to resume
        _, stderr = first.communicate(timeout=60)
    assert first.returncode in (0, 1) and "Traceback" not in stderr, stderr
    assert json.loads((out / "state.json").read_text())["images"]["count"] == 4


def test_training_temp_files_are_unique_per_process(tmp_path, monkeypatch):
    from sekd_sfm.files import atomic as fsio
    from sekd_sfm.train import report

    seen, real_replace = [], os.replace

    def spy(src, dst):
        seen.append(Path(src).name)
        real_replace(src, dst)

    monkeypatch.setattr(fsio.os, "replace", spy)
    report.write_atomic(tmp_path / "losses.csv", "a,b\n")
    assert seen == [f"losses.csv.{os.getpid()}.tmp"] and (tmp_path / "losses.csv").read_text() == "a,b\n"


def test_atomic_output_leaves_the_old_file_when_the_writer_fails(tmp_path):
    from sekd_sfm.files.atomic import atomic_output

    target = tmp_path / "sub" / "pairs.txt"
    target.parent.mkdir()
    target.write_text("old\n")
    with pytest.raises(RuntimeError), atomic_output(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("disk went away")
    assert target.read_text() == "old\n" and sorted(p.name for p in target.parent.iterdir()) == ["pairs.txt"]
    with atomic_output(tmp_path / "new" / "x.bin") as tmp:  # the parent folder is created
        tmp.write_bytes(b"\x00\x01")
    assert (tmp_path / "new" / "x.bin").read_bytes() == b"\x00\x01" and len(list((tmp_path / "new").iterdir())) == 1


def test_debug_variable_and_pixel_cap_are_documented():
    assert "SEKD_DEBUG=1" in CliRunner().invoke(sekd, ["--help"]).output
    doctor = CliRunner().invoke(sekd, ["doctor"], env={"SEKD_DEBUG": "1"})
    assert doctor.exit_code == 0 and "SEKD_DEBUG=1 (on: failures show the traceback)" in doctor.output
    assert "100 MP per image" in doctor.output
    assert "--max-pixels" in CliRunner().invoke(sekd, ["extract", "--help"]).output
