"""``--executor ray``: the same files as ``--executor local``, on a real two-raylet Ray cluster.

The cluster runs inside a network namespace made by the test (only ``lo`` up), so Ray binds
127.0.0.1 and nothing leaves the machine; one cluster serves every test of the module and is
stopped by the namespace's PIDs, also on failure. Needs root (``ip netns``) and ``ray``.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import SHARED
from sekd_sfm.cli.main import sekd

from sekd_sfm.extract import extract_features
from sekd_sfm.features import FeatureConfig
from sekd_sfm.match import match_features

COCO = SHARED / "data/train/coco"
SEKD_BIN = str(Path(sys.executable).with_name("sekd")) if Path(sys.executable).with_name("sekd").exists() else "sekd"


def _sh(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(args, check=False, capture_output=True, text=True, timeout=timeout)


def _namespace_pids(ns: str) -> list[int]:
    out = _sh("ip", "netns", "pids", ns).stdout
    return [int(p) for p in out.split()]


def _stop_namespace(ns: str, temp_dir: Path) -> None:
    """Kill every process of the namespace (ours: Ray's), then delete it."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in _namespace_pids(ns):
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + 3
        while _namespace_pids(ns) and time.monotonic() < deadline:
            time.sleep(0.2)
    _sh("ip", "netns", "del", ns)
    shutil.rmtree(temp_dir, ignore_errors=True)


@pytest.fixture(scope="module")
def cluster():
    """``(namespace, address)`` of a two-raylet Ray cluster (1 CPU each) on the namespace's loopback."""
    pytest.importorskip("ray", reason='ray is not installed (pip install "sekd-sfm[ray]")')
    if shutil.which("ip") is None:
        pytest.skip("ip (iproute2) not found: the Ray cluster needs a network namespace")
    ns, port = f"sekdray{os.getpid()}", 20000 + os.getpid() % 20000
    made = _sh("ip", "netns", "add", ns)
    if made.returncode != 0:
        pytest.skip(f"cannot create a network namespace (needs root): {made.stderr.strip()}")
    temp_dir = Path(f"/tmp/sekdray{os.getpid()}")
    try:
        _sh("ip", "netns", "exec", ns, "ip", "link", "set", "lo", "up")
        common = ("--num-cpus", "1", "--object-store-memory", str(200 << 20), "--disable-usage-stats")
        head = _sh("ip", "netns", "exec", ns, "ray", "start", "--head", "--port", str(port),
                   "--include-dashboard=false", "--temp-dir", str(temp_dir), *common)
        assert head.returncode == 0, head.stderr[-2000:]
        node = _sh("ip", "netns", "exec", ns, "ray", "start", "--address", f"127.0.0.1:{port}", *common)
        assert node.returncode == 0, node.stderr[-2000:]
        yield ns, f"127.0.0.1:{port}"
    finally:
        _stop_namespace(ns, temp_dir)


def _ray_cli(cluster, *args: str) -> list[str]:
    ns, address = cluster
    return ["ip", "netns", "exec", ns, SEKD_BIN, *args, "--executor", "ray", "--ray-address", address]


def _contents(path: Path) -> dict:
    """Every dataset of an HDF5 file as (dtype, shape, raw bytes), by path."""
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, (obj.dtype.str, obj.shape, obj[()].tobytes()))
                     if isinstance(obj, h5py.Dataset) else None)
    return out


def _attrs(path: Path, names=("config", "failed_images", "features_config", "feature_type")) -> dict:
    with h5py.File(path, "r") as f:
        return {n: str(f.attrs[n]) for n in names if n in f.attrs}


def _photos(folder: Path, count: int, bad: bool = False) -> Path:
    """``count`` shared COCO photos linked (not copied) into ``folder``; ``bad`` adds an undecodable one."""
    if not COCO.is_dir():
        pytest.skip(f"shared data not found at {COCO}")
    folder.mkdir()
    for src in sorted(COCO.iterdir())[:count]:
        (folder / src.name).symlink_to(src)
    if bad:
        (folder / "broken.jpg").write_bytes(b"not a jpeg")
    return folder


@pytest.fixture(scope="module")
def local_run(tmp_path_factory):
    """Local extraction and matching of 5 photos (+ a broken file) at 160 px: the reference.

    One torch thread, as each Ray worker (--threads-per-worker 1): torch rounds differently
    with the thread count, and the comparison is bit for bit.
    """
    root = tmp_path_factory.mktemp("local")
    images = _photos(root / "images", 5, bad=True)
    config = FeatureConfig(resize_max=160, max_keypoints=300)
    features = extract_features(images, root / "features.h5", config, progress=False, num_threads=1)
    pairs = root / "pairs.txt"
    names = sorted(p.name for p in images.iterdir() if p.name != "broken.jpg")
    pairs.write_text("".join(f"{a} {b}\n" for i, a in enumerate(names) for b in names[i + 1:]))
    matches = match_features(features, pairs, root / "matches.h5", progress=False, num_threads=1)
    return images, features, pairs, matches


def test_extract_on_ray_identical_to_local(cluster, local_run, tmp_path):
    images, features, _, _ = local_run
    out = tmp_path / "features.h5"
    run = subprocess.run(_ray_cli(cluster, "extract", str(images), "-o", str(out), "--resize-max", "160",
                                  "--max-keypoints", "300", "--no-progress"), check=False, capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "broken.jpg: not a decodable image" in run.stdout + run.stderr  # reported like any unreadable image
    assert _contents(out) == _contents(features)  # same keys, same arrays, byte for byte
    assert _attrs(out) == _attrs(features)
    assert '"broken.jpg"' in _attrs(out)["failed_images"]


def test_match_on_ray_identical_to_local(cluster, local_run, tmp_path):
    _, features, pairs, matches = local_run
    out = tmp_path / "matches.h5"
    run = subprocess.run(_ray_cli(cluster, "match", str(features), str(pairs), "-o", str(out), "--no-progress"),
                         check=False, capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    assert len(_contents(out)) == 2 * 10  # 10 pairs x (matches0, matching_scores0)
    assert _contents(out) == _contents(matches)
    assert _attrs(out) == _attrs(matches)


def _map_workers(ns: str) -> list[int]:
    """PIDs of Ray Data's map actors (process title ``ray::MapWorker(...)``) in the namespace."""
    pids = []
    for pid in _namespace_pids(ns):
        try:
            title = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue
        if title.startswith("ray::MapWorker"):
            pids.append(pid)
    return pids


def test_worker_killed_mid_run_is_redone(cluster, tmp_path):
    """kill -9 of a busy worker: Ray restarts it, its in-flight images are redone, the file is complete and right."""
    images = _photos(tmp_path / "images", 24)
    args = ["extract", str(images), "--resize-max", "320", "--max-keypoints", "300"]
    driver = subprocess.Popen(_ray_cli(cluster, *args, "-o", str(tmp_path / "ray.h5")),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    seen, killed, buffer = 0, None, b""
    deadline = time.monotonic() + 150
    while killed is None and time.monotonic() < deadline:
        chunk = os.read(driver.stderr.fileno(), 4096)
        if not chunk:
            break
        buffer = (buffer + chunk)[-4096:]
        done = re.findall(rb"(\d+)/24 \[", buffer)
        seen = int(done[-1]) if done else 0
        workers = _map_workers(cluster[0])
        if 4 <= seen <= 16 and workers:  # the first results are in, the rest in flight: kill a busy worker
            killed = workers[0]
            os.kill(killed, signal.SIGKILL)
    rest = driver.communicate(timeout=240)[1]
    assert killed is not None, f"no worker to kill while the run went on (last progress {seen}/24)"
    assert driver.returncode == 0, rest.decode(errors="replace")[-3000:]
    assert not Path(f"/proc/{killed}").exists()
    local = extract_features(images, tmp_path / "local.h5", FeatureConfig(resize_max=320, max_keypoints=300),
                             progress=False, num_threads=1)
    got = _contents(tmp_path / "ray.h5")
    assert len({name.split("/")[0] for name in got}) == 24
    assert got == _contents(local)


def test_missing_ray_is_one_error_line(tmp_path, monkeypatch):
    images = _photos(tmp_path / "images", 1)
    monkeypatch.setitem(sys.modules, "ray", None)  # ``import ray`` now raises ImportError
    out = tmp_path / "features.h5"
    result = CliRunner().invoke(sekd, ["extract", str(images), "-o", str(out), "--executor", "ray"])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: ")
    assert 'pip install "sekd-sfm[ray]"' in lines[0]
    assert not out.exists()  # refused before anything was written
    result = CliRunner().invoke(sekd, ["match", str(out), str(tmp_path / "pairs.txt"), "--executor", "ray"])
    assert result.exit_code == 1 and 'pip install "sekd-sfm[ray]"' in result.output


def test_results_travel_bit_for_bit():
    from sekd_sfm.cluster import _pack, _unpack

    rng = np.random.default_rng(0)
    arrays = {"keypoints": rng.normal(size=(7, 2)).astype(np.float32), "descriptors": rng.integers(0, 255, (7, 32), np.uint8),
              "scores": np.array([np.nan, -0.0, 1e-42, np.inf, 0, 1, 2], np.float32), "image_size": np.array([640, 480], np.int32),
              "uncertainty": np.float32(1.25), "empty": np.zeros((0, 128), np.float32)}
    back = _unpack(_pack(arrays))
    assert sorted(back) == sorted(arrays)
    for name, value in arrays.items():
        assert back[name].dtype == value.dtype and back[name].shape == value.shape
        assert back[name].tobytes() == value.tobytes()


class _FakeRay:
    def __init__(self, **resources):
        self.resources = resources

    def cluster_resources(self):
        return self.resources


@pytest.mark.parametrize(("resources", "options", "expected"), [
    ({"CPU": 8.0}, {}, 8),
    ({"CPU": 8.0}, {"threads_per_worker": 3}, 2),
    ({"CPU": 8.0}, {"workers": 3}, 3),
    ({"CPU": 8.0}, {"workers": 30}, 8),
    ({"CPU": 16.0, "GPU": 2.0}, {"gpus_per_worker": 0.5, "threads_per_worker": 2}, 4),
    ({"CPU": 4.0, "GPU": 8.0}, {"gpus_per_worker": 1}, 4),
])
def test_worker_count_fits_the_cluster(resources, options, expected):
    from sekd_sfm.cluster import RayOptions, _workers

    assert _workers(_FakeRay(**resources), RayOptions(**options)) == expected


@pytest.mark.parametrize(("resources", "options", "message"), [
    ({"CPU": 2.0}, {"threads_per_worker": 4}, "--threads-per-worker 4 but the Ray cluster has 2 CPUs"),
    ({"CPU": 2.0}, {"gpus_per_worker": 1}, "--gpus-per-worker 1 but the Ray cluster has 0 GPUs"),
])
def test_worker_size_larger_than_the_cluster_is_refused(resources, options, message):
    from sekd_sfm.cluster import RayOptions, _workers
    from sekd_sfm.errors import SekdError

    with pytest.raises(SekdError, match=re.escape(message)):
        _workers(_FakeRay(**resources), RayOptions(**options))


def test_unknown_executor_is_refused(tmp_path):
    from sekd_sfm.errors import SekdError

    with pytest.raises(SekdError, match="unknown executor 'spark'; choose from local, ray"):
        extract_features(tmp_path, tmp_path / "f.h5", executor="spark")
    assert not (tmp_path / "f.h5").exists()


def _closed_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_no_cluster_at_the_address_is_one_error_line(tmp_path):
    """Refused at once, before Ray starts anything (Ray alone retries for minutes)."""
    pytest.importorskip("ray", reason='ray is not installed (pip install "sekd-sfm[ray]")')
    images = _photos(tmp_path / "images", 1)
    address = f"127.0.0.1:{_closed_port()}"
    result = CliRunner().invoke(sekd, ["extract", str(images), "-o", str(tmp_path / "f.h5"), "--executor", "ray",
                                       "--ray-address", address])
    assert result.exit_code == 1
    assert result.output.strip().splitlines()[-1].startswith(f"Error: no Ray cluster answers at {address} (")
    assert "ray start --head" in result.output
    result = CliRunner().invoke(sekd, ["extract", str(images), "--executor", "ray", "--ray-address", "headnode"])
    assert result.exit_code == 1 and "expected HOST:PORT" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images"]  # refused before anything was written
