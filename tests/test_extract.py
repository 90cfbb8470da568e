"""`sekd extract`: file layout, resume after a crash, bad input, CLI."""
import json
import os
import signal
import subprocess
import sys
import time

import cv2
import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import SEKD_WEIGHTS

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.features import FeatureConfig
from sekd_sfm.files import features as ff
from sekd_sfm.files import partstore
from sekd_sfm.model.inference import SEKDConfig
from sekd_sfm.stages.extract import extract_features


def textured(seed: int, shape=(120, 160)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = cv2.resize((rng.random((shape[0] // 8, shape[1] // 8)) * 255).astype(np.uint8), shape[::-1],
                       interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(image, (3, 3), 0)


def write_images(folder, names, shape=(120, 160)):
    for i, name in enumerate(names):
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / name), textured(i, shape))
    return folder


def sekd_config(**kw) -> FeatureConfig:
    return FeatureConfig(feature="sekd", max_keypoints=kw.pop("max_keypoints", 200), weights=str(SEKD_WEIGHTS),
                         sekd=SEKDConfig(precision="fp32", device="cpu"), **kw)


@pytest.fixture
def images(tmp_path):
    return write_images(tmp_path / "images", ["a.png", "sub dir/b ü.jpg", "c.pgm"])


def test_hloc_layout_and_attributes(images, tmp_path, shared):
    out = extract_features(images, tmp_path / "f.h5", sekd_config(), progress=False)
    assert ff.list_keys(out) == ["a.png", "c.pgm", "sub dir/b ü.jpg"]
    with h5py.File(out) as f:
        group = f["sub dir/b ü.jpg"]
        n = group["keypoints"].shape[0]
        assert 0 < n <= 200
        assert group["keypoints"].dtype == np.float32 and group["keypoints"].shape == (n, 2)
        assert group["descriptors"].shape == (128, n)  # D x N as hloc
        assert group["scores"].shape == (n,)
        assert group["image_size"][()].tolist() == [160, 120]
        assert f.attrs["feature_type"] == "sekd" and f.attrs["descriptor_dim"] == 128
        assert json.loads(f.attrs["config"])["sekd"]["precision"] == "fp32"
        assert len(f.attrs["model_sha256"]) == 16 and "torch" in json.loads(f.attrs["versions"])
    features = ff.read_features(out, "a.png")
    assert np.allclose(np.linalg.norm(features["descriptors"], axis=1), 1, atol=1e-5)
    assert not (tmp_path / "f.h5.parts").exists()


@pytest.mark.parametrize("feature,dim,dtype", [("sift", 128, np.float32), ("orb", 32, np.uint8),
                                               ("akaze", 61, np.uint8), ("brisk", 64, np.uint8),
                                               ("kaze", 64, np.float32)])
def test_classic_features_same_format(tmp_path, feature, dim, dtype):
    images = write_images(tmp_path / "im", ["x.png"], shape=(240, 320))
    out = extract_features(images, tmp_path / "f.h5", FeatureConfig(feature=feature, max_keypoints=100), progress=False)
    features = ff.read_features(out, "x.png")
    n = len(features["keypoints"])
    assert 0 < n <= 100
    assert features["descriptors"].shape == (n, dim) and features["descriptors"].dtype == dtype
    assert np.all(np.diff(features["scores"]) <= 0)


def test_resize_max_maps_keypoints_back(tmp_path, shared):
    small = textured(3, (96, 128))
    big = cv2.resize(small, (256, 192), interpolation=cv2.INTER_NEAREST)  # area-downscaling gives `small` back
    folder = tmp_path / "im"
    folder.mkdir()
    cv2.imwrite(str(folder / "small.png"), small)
    cv2.imwrite(str(folder / "big.png"), big)
    out = extract_features(folder, tmp_path / "f.h5", sekd_config(resize_max=128), progress=False)
    kp_small = ff.read_features(out, "small.png")["keypoints"]
    kp_big = ff.read_features(out, "big.png")
    assert kp_big["image_size"].tolist() == [256, 192]
    assert np.allclose(kp_big["keypoints"], (kp_small + 0.5) * 2 - 0.5)


def test_resume_after_crash_before_merge(images, tmp_path, monkeypatch, shared):
    """A run killed after saving parts but before merging: the file opens, the next run completes it."""
    out = tmp_path / "f.h5"
    real_merge = partstore.merge_parts
    monkeypatch.setattr(partstore, "merge_parts", lambda *a, **k: (_ for _ in ()).throw(SystemExit("killed")))
    with pytest.raises(SystemExit):
        extract_features(images, out, sekd_config(), progress=False)
    assert ff.list_keys(out) == []  # opens, holds nothing yet
    monkeypatch.setattr(partstore, "merge_parts", real_merge)
    calls = []
    import sekd_sfm.stages.extract as ex
    real_features_of = ex._features_of
    monkeypatch.setattr(ex, "_features_of", lambda *a: calls.append(1) or real_features_of(*a))
    extract_features(images, out, sekd_config(), progress=False)
    assert calls == []  # every image came from the saved parts
    assert ff.list_keys(out) == ["a.png", "c.pgm", "sub dir/b ü.jpg"]


def test_kill_9_at_any_moment_leaves_a_readable_file(tmp_path):
    """Killed while parts are being written (checkpoint_seconds=0: one chunk per image) or while merging."""
    images = write_images(tmp_path / "im", [f"{i:03d}.png" for i in range(40)], shape=(240, 320))
    out = tmp_path / "f.h5"
    script = ("from sekd_sfm.stages.extract import extract_features; from sekd_sfm.features import FeatureConfig; "
              f"extract_features({str(images)!r}, {str(out)!r}, FeatureConfig(feature='sift', max_keypoints=300), "
              "progress=False, checkpoint_seconds=0)")
    proc = subprocess.Popen([sys.executable, "-c", script])
    parts = tmp_path / "f.h5.parts"
    deadline = time.monotonic() + 60
    while not (parts.is_dir() and len(list(parts.glob("*.npz"))) >= 5) and time.monotonic() < deadline \
            and proc.poll() is None:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    first = ff.list_keys(out)  # opens after the kill
    saved = partstore.PartStore(out).keys()
    calls = []
    import sekd_sfm.stages.extract as ex
    real = ex._features_of
    ex._features_of = lambda *a: calls.append(1) or real(*a)
    try:
        extract_features(images, out, FeatureConfig(feature="sift", max_keypoints=300), progress=False)
    finally:
        ex._features_of = real
    assert len(calls) == 40 - len(set(first) | saved)  # saved images are not recomputed
    clean = extract_features(images, tmp_path / "clean.h5", FeatureConfig(feature="sift", max_keypoints=300), progress=False)
    assert ff.list_keys(out) == ff.list_keys(clean) == [f"{i:03d}.png" for i in range(40)]
    assert set(first) <= set(ff.list_keys(out))
    for key in ff.list_keys(out):
        a, b = ff.read_features(out, key), ff.read_features(clean, key)
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_corrupt_image_skipped_and_counted(images, tmp_path, shared):
    (images / "broken.jpg").write_bytes(b"\xff\xd8 not really")
    out = extract_features(images, tmp_path / "f.h5", FeatureConfig(feature="sift"), progress=False)
    with h5py.File(out) as f:
        assert json.loads(f.attrs["failed_images"]) == ["broken.jpg"]
    assert "broken.jpg" not in ff.list_keys(out)
    with pytest.raises(SekdError, match="broken.jpg.*--strict"):
        extract_features(images, tmp_path / "g.h5", FeatureConfig(feature="sift"), strict=True, progress=False)


def test_skip_warnings_go_to_stderr_and_stdout_holds_only_the_output(images, tmp_path):
    """Scripts read the output's path from stdout (``F=$(sekd extract ...)``): warnings must not land there."""
    (images / "broken.jpg").write_bytes(b"\xff\xd8 not really")
    out = tmp_path / "f.h5"
    result = CliRunner().invoke(sekd, ["extract", str(images), "-o", str(out), "--feature", "sift", "--no-progress"])
    assert result.exit_code == 0, result.output
    assert result.stdout == f"{out}\n"
    assert "warning: " in result.stderr and "broken.jpg" in result.stderr and "skipped" in result.stderr


def test_mismatched_configuration_is_refused(images, tmp_path):
    out = extract_features(images, tmp_path / "f.h5", FeatureConfig(feature="sift", max_keypoints=100), progress=False)
    with pytest.raises(SekdError, match="different configuration"):
        extract_features(images, out, FeatureConfig(feature="sift", max_keypoints=50), progress=False)
    extract_features(images, out, FeatureConfig(feature="sift", max_keypoints=50), overwrite=True, progress=False)
    assert all(len(ff.read_features(out, k)["keypoints"]) <= 50 for k in ff.list_keys(out))


def test_output_that_is_not_a_feature_file(images, tmp_path):
    (tmp_path / "notes.h5").write_text("hello")
    with pytest.raises(SekdError, match="not a readable HDF5"):
        extract_features(images, tmp_path / "notes.h5", FeatureConfig(feature="sift"), progress=False)
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = 1
    with pytest.raises(SekdError, match="not a sekd feature file"):
        extract_features(images, tmp_path / "other.h5", FeatureConfig(feature="sift"), progress=False)


def test_cli_extract_and_errors(images, tmp_path, shared):
    runner = CliRunner()
    out = tmp_path / "f.h5"
    result = runner.invoke(sekd, ["extract", str(images), "-o", str(out), "--weights", str(SEKD_WEIGHTS),
                                  "--max-keypoints", "50", "--precision", "fp32", "--no-progress"])
    assert result.exit_code == 0, result.output
    assert len(ff.list_keys(out)) == 3
    result = runner.invoke(sekd, ["extract", str(tmp_path / "nowhere"), "-o", str(out)])
    assert result.exit_code == 1
    assert result.output.strip().splitlines() == [(f"Error: {tmp_path / 'nowhere'}: image folder not found; "
                                                   "give a folder that contains images")]
    result = runner.invoke(sekd, ["extract", str(images), "-o", str(out), "--weights", str(tmp_path / "no.pth")])
    assert result.exit_code == 1 and "weights file not found" in result.output


def test_cli_version_and_doctor():
    runner = CliRunner()
    assert runner.invoke(sekd, ["--version"]).output.startswith("sekd, version")
    result = runner.invoke(sekd, ["doctor"])
    assert result.exit_code == 0 and "avx512_bf16" in result.output and "embedded model" in result.output


def test_doctor_lists_the_optional_extras(monkeypatch):
    """Each extra: its packages' versions, or the install command (from package metadata, nothing imported)."""
    import importlib.metadata

    from sekd_sfm.cli import doctor

    real = importlib.metadata.version

    def version(name: str) -> str:
        if name in ("openvino", "ray"):
            raise importlib.metadata.PackageNotFoundError(name)
        return {"nncf": "9.9", "plotly": "1.2.3"}.get(name) or real(name)

    monkeypatch.setattr(importlib.metadata, "version", version)
    assert doctor._extras() == {
        "extra ray": 'not installed (--executor ray: pip install "sekd-sfm[ray]")',
        "extra int8": 'not installed (--precision int8: pip install "sekd-sfm[int8]")',
        "extra viz": "plotly 1.2.3 (export --format html)",
    }
    monkeypatch.setattr(importlib.metadata, "version", lambda name: {"ray": "2.60.0"}.get(name) or version(name))
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.5:6379")
    extras = doctor._extras()
    assert extras["extra ray"] == "ray 2.60.0 (--executor ray)"
    assert extras["ray cluster here"] == "$RAY_ADDRESS=10.0.0.5:6379 (what --ray-address auto uses)"


def test_cpu_description_matches_the_flags_the_kernel_reports():
    from sekd_sfm.runtime import CPU_FEATURES, cpu_description, cpu_flags

    described = cpu_description()
    flags = cpu_flags()
    assert list(described["features"]) == list(CPU_FEATURES)
    assert all(present == (name in flags) for name, present in described["features"].items())
    assert described["model"] and described["cores"] == os.cpu_count()
    assert described["torch_kernels"] == torch.backends.cpu.get_cpu_capability()


def test_sigterm_stops_cleanly_and_the_next_run_completes(tmp_path):
    images = write_images(tmp_path / "im", [f"{i:03d}.png" for i in range(60)], shape=(240, 320))
    out = tmp_path / "f.h5"
    proc = subprocess.Popen([sys.executable, "-m", "sekd_sfm.cli.main", "extract", str(images), "-o", str(out),
                             "--feature", "sift", "--no-progress"], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    lock = tmp_path / "f.h5.lock"  # holds the PID once the run has started
    while not (lock.exists() and lock.read_text().strip()) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.02)
    time.sleep(0.3)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=60)
    if proc.returncode != 0:  # stopped mid-run or mid-merge: one error line saying how to resume
        errors = [line for line in stderr.splitlines() if line.startswith("Error:")]
        assert proc.returncode == 1 and len(errors) == 1, stderr
        assert "interrupted" in errors[0] and "run the same command again" in errors[0]
        assert "Traceback" not in stderr
    saved = ff.list_keys(out)  # opens
    extract_features(images, out, FeatureConfig(feature="sift"), progress=False)
    assert set(saved) <= set(ff.list_keys(out)) and len(ff.list_keys(out)) == 60
    assert not (tmp_path / "f.h5.parts").exists()


def test_summary_line_counts_images_merged_at_checkpoints(tmp_path, caplog):
    """Parts merged at a checkpoint during the run still count as written by it."""
    write_images(tmp_path / "img", ["a.png", "b.png", "c.png"])
    caplog.set_level("INFO", logger="sekd")
    extract_features(tmp_path / "img", tmp_path / "f.h5", FeatureConfig(feature="sift"), progress=False,
                     checkpoint_seconds=0.0)
    assert "3 images written this run, 0 failed, 3 in the file" in caplog.text


def test_cli_keypoints_are_sub_pixel_by_default_and_integer_with_no_subpixel(images, tmp_path, shared):
    from click.testing import CliRunner

    from sekd_sfm.cli.main import sekd

    runs = {}
    for flag in ([], ["--no-subpixel"]):
        out = tmp_path / f"f{len(flag)}.h5"
        result = CliRunner().invoke(sekd, ["extract", str(images), "-o", str(out), "--weights", str(SEKD_WEIGHTS),
                                           "--max-keypoints", "200", "--precision", "fp32", "--num-threads", "1", *flag])
        assert result.exit_code == 0, result.output
        runs[bool(flag)] = ff.read_features(out, "a.png")["keypoints"]
    refined, integer = runs[False], runs[True]
    assert np.array_equal(integer, np.round(integer))  # the peak's pixel centre
    assert (refined != np.round(refined)).mean() > 0.5  # most keypoints move off the pixel centre
    assert np.abs(refined - np.round(refined)).max() <= 1.0 and len(refined) == len(integer)


HEAP_PROBE = """
import sys
import numpy as np
from sekd_sfm.bench.scale.measure import proc_status
from sekd_sfm.stages.extract import extract_features
from sekd_sfm.features import FeatureConfig
from sekd_sfm.runtime import tune_allocator

def rss():
    return proc_status()["VmRSS"]

if sys.argv[1] == "extract":  # the network tunes the allocator, extract_features undoes it at the end
    extract_features(sys.argv[2], sys.argv[3], FeatureConfig(feature="sekd", max_keypoints=100), progress=False)
else:  # control: the network's thresholds left in place
    tune_allocator()
before = rss()
block = np.ones(256 << 20, dtype=np.uint8)  # 256 MB, touched
del block
print((rss() - before) >> 20)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator (mallopt) and /proc")
def test_extraction_gives_the_heap_back_to_the_stages_after_it(tmp_path):
    """After extract_features a freed 256 MB array leaves the process; under the network's thresholds it stays."""
    images = write_images(tmp_path / "im", ["a.png", "b.png"])

    def kept_mb(*args):
        done = subprocess.run([sys.executable, "-c", HEAP_PROBE, *args], capture_output=True, text=True, timeout=300,
                              env={**os.environ, "OMP_NUM_THREADS": "1"}, check=False)
        assert done.returncode == 0, done.stderr
        return int(done.stdout.split()[-1])

    assert kept_mb("tuned") >= 200  # the heap keeps what was freed: the case the untuning exists for
    assert kept_mb("extract", str(images), str(tmp_path / "f.h5")) < 32
    with h5py.File(tmp_path / "f.h5", "r") as f:
        assert sorted(f) == ["a.png", "b.png"]
