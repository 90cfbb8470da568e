"""``--executor ray``: the same files as ``--executor local``, on a real two-raylet Ray cluster.

The cluster runs inside a network namespace made by the test (only ``lo`` up), so Ray binds
127.0.0.1 and nothing leaves the machine; one cluster serves every test of the module and is
stopped by the namespace's PIDs, also on failure. Needs root (``ip netns``) and ``ray``; the ``ray``
and ``sekd`` commands are the ones installed beside this Python (``venv/bin/python -m pytest`` works
without activating the venv), and the tests that need one skip when it is not there.
"""
from __future__ import annotations

import contextlib
import json
import os
import pickle
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import SHARED

from sekd_sfm.cli.main import sekd
from sekd_sfm.features import FeatureConfig
from sekd_sfm.stages.extract import extract_features
from sekd_sfm.stages.match import match_features

COCO = SHARED / "data/train/coco"


def _installed(command: str) -> str:
    """The console script ``command`` installed beside this Python (a venv's ``bin``), not one found on ``$PATH``;
    the test skips when it is absent."""
    path = Path(sys.executable).parent / command
    if not path.is_file():
        pytest.skip(f"{command!r} is not installed beside {sys.executable} (looked for {path}): "
                    f'pip install -e ".[dev]" with this Python installs it')
    return str(path)


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
    ray = _installed("ray")
    ns, port = f"sekdray{os.getpid()}", 20000 + os.getpid() % 20000
    made = _sh("ip", "netns", "add", ns)
    if made.returncode != 0:
        pytest.skip(f"cannot create a network namespace (needs root): {made.stderr.strip()}")
    temp_dir = Path(f"/tmp/sekdray{os.getpid()}")
    try:
        _sh("ip", "netns", "exec", ns, "ip", "link", "set", "lo", "up")
        common = ("--num-cpus", "1", "--object-store-memory", str(200 << 20), "--disable-usage-stats")
        head = _sh("ip", "netns", "exec", ns, ray, "start", "--head", "--port", str(port),
                   "--include-dashboard=false", "--temp-dir", str(temp_dir), *common)
        assert head.returncode == 0, head.stderr[-2000:]
        node = _sh("ip", "netns", "exec", ns, ray, "start", "--address", f"127.0.0.1:{port}", *common)
        assert node.returncode == 0, node.stderr[-2000:]
        yield ns, f"127.0.0.1:{port}"
    finally:
        _stop_namespace(ns, temp_dir)


def _ray_cli(cluster, *args: str) -> list[str]:
    ns, address = cluster
    return ["ip", "netns", "exec", ns, _installed("sekd"), *args, "--executor", "ray", "--ray-address", address]


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


@pytest.mark.parametrize("merge", ["copy", "virtual"])
def test_extract_on_ray_identical_to_local(cluster, local_run, tmp_path, merge):
    images, features, _, _ = local_run
    out = tmp_path / "features.h5"
    run = subprocess.run(_ray_cli(cluster, "extract", str(images), "-o", str(out), "--resize-max", "160",
                                  "--max-keypoints", "300", "--no-progress", "--ray-merge", merge),
                         check=False, capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    with h5py.File(out, "r") as f:  # virtual: the file references the workers' shard files
        assert f[f"{min(f.keys())}/descriptors"].is_virtual == (merge == "virtual")
    assert "broken.jpg: not a decodable image" in run.stdout + run.stderr  # reported like any unreadable image
    assert _contents(out) == _contents(features)  # same keys, same arrays, byte for byte
    assert _attrs(out) == _attrs(features)
    assert '"broken.jpg"' in _attrs(out)["failed_images"]
    _assert_keys_only(run.stderr, "img")


def _assert_keys_only(log: str, unit: str) -> None:
    """The driver's summary line: it received keys (~100 B per item), not the arrays (a result is > 50 kB here)."""
    received = re.findall(rf"driver received (\d+) B per {unit}", log)
    assert received and int(received[-1]) < 500, log[-2000:]


def _library_extract(cluster, images: Path, out: Path, config: str, ray_options: str, progress: bool = False) -> list[str]:
    """The command running ``extract_features(images, out, FeatureConfig(CONFIG), executor='ray',
    ray_options=RayOptions(address=..., RAY_OPTIONS))`` in the namespace (options the CLI does not
    offer), INFO log on stderr, the output's path on stdout."""
    ns, address = cluster
    script = ("import logging, sys\n"
              "logging.basicConfig(level=logging.INFO, format='%(message)s')\n"
              "from sekd_sfm.execution import RayOptions\n"
              "from sekd_sfm.stages.extract import extract_features\n"
              "from sekd_sfm.features import FeatureConfig\n"
              f"print(extract_features(sys.argv[1], sys.argv[2], FeatureConfig({config}), progress={progress}, "
              f"executor='ray', ray_options=RayOptions(address=sys.argv[3], {ray_options})))\n")
    return ["ip", "netns", "exec", ns, sys.executable, "-c", script, str(images), str(out), address]


def test_driver_helping_gives_the_same_file(cluster, local_run, tmp_path):
    """The driver's own extraction while workers start (forced on: this cluster holds every core) changes nothing."""
    images, features, _, _ = local_run
    out = tmp_path / "features.h5"
    run = subprocess.run(_library_extract(cluster, images, out, "resize_max=160, max_keypoints=300", "driver_helps=True"),
                         check=False, capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    helped = re.findall(r"the driver extracted (\d+) of the 6 images itself", run.stderr)  # 5 photos + broken.jpg
    assert helped and 1 <= int(helped[-1]) <= 3, run.stderr[-2000:]  # from the end of the list, never over half
    assert _contents(out) == _contents(features)
    assert _attrs(out) == _attrs(features)
    assert not list(tmp_path.glob("*.claims-*"))  # the run's claims file is gone


def test_match_on_ray_identical_to_local(cluster, local_run, tmp_path):
    _, features, pairs, matches = local_run
    out = tmp_path / "matches.h5"
    run = subprocess.run(_ray_cli(cluster, "match", str(features), str(pairs), "-o", str(out), "--no-progress"),
                         check=False, capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    assert len(_contents(out)) == 2 * 10  # 10 pairs x (matches0, matching_scores0)
    assert _contents(out) == _contents(matches)
    assert _attrs(out) == _attrs(matches)
    _assert_keys_only(run.stderr, "pair")


def test_global_descriptors_on_ray_identical_to_local(cluster, local_run, tmp_path):
    """``sekd pairs --pairs retrieval --executor ray``: the vocabulary's groups and each photo's VLAD on the workers
    (the sample's PCA and split in the driver); the vocabulary, the global descriptors and the pairs those of a local
    run."""
    _, features, _, _ = local_run
    copy = shutil.copy(features, tmp_path / "features.h5")
    here = tmp_path / "here"
    here.mkdir()
    shutil.copy(features, here / "features.h5")
    run = subprocess.run(_ray_cli(cluster, "pairs", str(copy), "-o", str(tmp_path / "pairs.txt"), "--pairs",
                                  "retrieval", "--num-neighbors", "2", "--no-progress"),
                         check=False, capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    assert re.search(r"Ray: 4 groups in ", run.stderr) and re.search(r"Ray: 5 imgs in ", run.stderr), run.stderr[-2000:]
    result = CliRunner().invoke(sekd, ["pairs", str(here / "features.h5"), "-o", str(here / "pairs.txt"), "--pairs",
                                       "retrieval", "--num-neighbors", "2", "--no-progress"])
    assert result.exit_code == 0, result.output[-2000:]
    with h5py.File(tmp_path / "features.global.h5", "r") as a, h5py.File(here / "features.global.h5", "r") as b:
        assert a["names"][()].tolist() == b["names"][()].tolist() and a.attrs["identity"] == b.attrs["identity"]
        assert np.array_equal(a["vocabulary/centroids"][()], b["vocabulary/centroids"][()])
        # The same numbers up to torch's reductions over threads (one per worker, the machine's here).
        assert np.allclose(a["descriptors"][()].astype(np.float32), b["descriptors"][()].astype(np.float32), atol=1e-3)
    assert (tmp_path / "pairs.txt").read_text() == (here / "pairs.txt").read_text()


def _map_workers(ns: str) -> list[int]:
    """PIDs of the run's actors (process title ``ray::_RunActor...``) in the namespace."""
    pids = []
    for pid in _namespace_pids(ns):
        try:
            title = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue
        if title.startswith("ray::_RunActor"):
            pids.append(pid)
    return pids


@pytest.fixture(scope="module")
def photos_320(tmp_path_factory):
    """24 photos and their local extraction at 320 px with one torch thread (the kill tests' reference)."""
    root = tmp_path_factory.mktemp("photos320")
    images = _photos(root / "images", 24)
    local = extract_features(images, root / "local.h5", FeatureConfig(resize_max=320, max_keypoints=300),
                             progress=False, num_threads=1)
    return images, _contents(local)


def _kill_when(driver: subprocess.Popen, total: int, victim) -> tuple[int | None, int]:
    """Read the driver's progress bar; once 4 to 16 of ``total`` are done, SIGKILL the PID ``victim()`` names.

    Returns ``(killed PID or None, last progress seen)``.
    """
    seen, buffer = 0, b""
    deadline = time.monotonic() + 150
    while time.monotonic() < deadline:
        chunk = os.read(driver.stderr.fileno(), 4096)
        if not chunk:
            break
        buffer = (buffer + chunk)[-4096:]
        done = re.findall(rb"(\d+)/%d \[" % total, buffer)
        seen = int(done[-1]) if done else 0
        pid = victim() if 4 <= seen <= 16 else None  # the first results are in, the rest in flight
        if pid:
            os.kill(pid, signal.SIGKILL)
            return pid, seen
    return None, seen


def test_worker_killed_mid_run_is_redone(cluster, photos_320, tmp_path):
    """kill -9 of a busy worker: Ray restarts it, its unfinished task is redone, the file is complete and identical."""
    images, local = photos_320
    args = ["extract", str(images), "--resize-max", "320", "--max-keypoints", "300"]
    driver = subprocess.Popen(_ray_cli(cluster, *args, "-o", str(tmp_path / "ray.h5")),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    killed, seen = _kill_when(driver, 24, lambda: next(iter(_map_workers(cluster[0])), None))
    rest = driver.communicate(timeout=240)[1]
    assert killed is not None, f"no worker to kill while the run went on (last progress {seen}/24)"
    assert driver.returncode == 0, rest.decode(errors="replace")[-3000:]
    assert not Path(f"/proc/{killed}").exists()
    got = _contents(tmp_path / "ray.h5")
    assert len({name.split("/")[0] for name in got}) == 24
    assert got == local
    assert not Path(f"{tmp_path / 'ray.h5'}.parts").exists()  # every chunk merged, no torn temporary left


def _workers_of(raylet: int) -> list[tuple[int, bool]]:
    """``(PID, busy)`` of the extraction workers a raylet started (its children); busy = running a task."""
    found = []
    for child in Path(f"/proc/{raylet}/task/{raylet}/children").read_text().split():
        try:
            title = Path(f"/proc/{child}/cmdline").read_bytes()
        except OSError:
            continue
        if title.startswith(b"ray::_RunActor"):
            found.append((int(child), title.startswith(b"ray::_RunActor.__call__")))
    return found


def test_node_leaving_mid_run_its_tasks_go_to_the_others(cluster, photos_320, tmp_path):
    """A third node joins, then its worker and raylet are killed mid-run (a machine leaving for
    good): the tasks its worker held are done by the other two, the file is complete and identical, one
    warning line says so, and nothing of Ray's reaches stdout (which holds only the output)."""
    ns, address = cluster
    name = f"leaving{os.getpid()}"
    before = set(_namespace_pids(ns))
    joined = _sh("ip", "netns", "exec", ns, _installed("ray"), "start", "--address", address, "--num-cpus", "1",
                 "--object-store-memory", str(200 << 20), "--disable-usage-stats", "--node-name", name)
    node = set(_namespace_pids(ns)) - before  # the third node's processes (no job runs yet)
    try:
        assert joined.returncode == 0, joined.stderr[-2000:]
        raylet = next(pid for pid in node
                      if f"--node-name={name}".encode() in Path(f"/proc/{pid}/cmdline").read_bytes())
        images, local = photos_320
        out = tmp_path / "ray.h5"
        # Tasks of one image, so the third node's worker surely holds some when the machine goes.
        driver = subprocess.Popen(_library_extract(cluster, images, out, "resize_max=320, max_keypoints=300",
                                                   "images_per_task=1", progress=True),
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        def machine_off() -> int | None:  # once its worker computes: the workers, then (by _kill_when) the raylet
            workers = _workers_of(raylet)
            if not any(busy for _, busy in workers):
                return None
            for pid, _ in workers:
                os.kill(pid, signal.SIGKILL)
            return raylet

        killed, seen = _kill_when(driver, 24, machine_off)
        stdout, stderr = driver.communicate(timeout=240)
        assert killed is not None, f"the run ended before the node could be stopped (last progress {seen}/24)"
        assert driver.returncode == 0, stderr.decode(errors="replace")[-3000:]
        assert stdout.decode() == f"{out}\n"
        assert "warning: a Ray worker stopped" in stderr.decode(errors="replace")
        assert _contents(out) == local
    finally:
        for pid in node:  # the rest of the third node (its agents), by PID
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        # The next tests expect two nodes: wait until Ray has marked the third one dead.
        wait = ("import ray, sys, time\nray.init(address=sys.argv[1], logging_level='ERROR')\n"
                "deadline = time.monotonic() + 90\n"
                "while sum(n['Alive'] for n in ray.nodes()) > 2 and time.monotonic() < deadline:\n    time.sleep(1)\n")
        _sh("ip", "netns", "exec", ns, sys.executable, "-c", wait, address, timeout=120)


def test_driver_killed_mid_run_resumes_without_redoing(cluster, photos_320, tmp_path):
    """kill -9 of the driver: the chunks the workers wrote stay, and the same command computes only the rest."""
    from sekd_sfm.files import partstore
    images, local = photos_320
    out = tmp_path / "ray.h5"
    command = _ray_cli(cluster, "extract", str(images), "--resize-max", "320", "--max-keypoints", "300", "-o", str(out))
    driver = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    killed, seen = _kill_when(driver, 24, lambda: driver.pid)
    driver.communicate(timeout=60)
    assert killed is not None, f"the driver finished before it could be killed (last progress {seen}/24)"
    kept = partstore.PartStore(out).keys()  # chunks written by the workers (more may land while Ray stops them)
    assert len(kept) >= seen >= 4
    rerun = subprocess.run(command + ["--no-progress"], check=False, capture_output=True, text=True, timeout=240)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    done = int(re.findall(r"24 images, (\d+) already done", rerun.stderr)[-1])
    assert done >= len(kept)  # nothing written before the kill is computed again
    if done < 24:  # (tasks in flight at the kill may all have finished: then nothing is left to do)
        helped = re.findall(r"the driver extracted (\d+) of the (\d+) images itself", rerun.stderr)
        by_driver = int(helped[-1][0]) if helped else 0  # while the workers start (ray_run._DriverHelper)
        assert not helped or int(helped[-1][1]) == 24 - done
        assert re.search(rf"Ray: {24 - done - by_driver} imgs in ", rerun.stderr), rerun.stderr[-2000:]
    assert _contents(out) == local
    assert not list(tmp_path.glob("*.tmp"))  # the killed driver's merge copy was removed by the rerun


def _sekd_in(ns: str, *args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """``sekd ARGS`` inside the namespace ``ns``, with ``env`` replacing ``$RAY_ADDRESS`` (None: unset)."""
    environ = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"} | (env or {})
    return subprocess.run(["ip", "netns", "exec", ns, _installed("sekd"), *args], env=environ, check=False,
                          capture_output=True, text=True, timeout=300)


def test_auto_address_finds_the_running_cluster(cluster, tmp_path):
    """``--ray-address auto`` (the default) without ``$RAY_ADDRESS`` joins the cluster ``ray start`` made here, although
    it has its own ``--temp-dir`` (``ray.init()`` alone would start a second, one-node cluster); an explicit address
    wins over ``$RAY_ADDRESS``; Ray's start-up notes stay out of the terminal."""
    ns, address = cluster
    images = _photos(tmp_path / "images", 2)
    args = ("extract", str(images), "--resize-max", "160", "--max-keypoints", "100", "--no-progress", "--executor", "ray")
    auto = _sekd_in(ns, *args, "-o", str(tmp_path / "auto.h5"))
    assert auto.returncode == 0, auto.stderr[-2000:]
    assert f"Ray: connected to the cluster at {address} (2 nodes, 2 CPUs)" in auto.stderr
    assert "network_util" not in auto.stderr and "logging.cc" not in auto.stderr, auto.stderr[-2000:]
    explicit = _sekd_in(ns, *args, "-o", str(tmp_path / "explicit.h5"), "--ray-address", address,
                        env={"RAY_ADDRESS": f"127.0.0.1:{_closed_port()}"})
    assert explicit.returncode == 0, explicit.stderr[-2000:]
    assert f"Ray: connected to the cluster at {address} (2 nodes" in explicit.stderr
    assert _contents(tmp_path / "auto.h5") == _contents(tmp_path / "explicit.h5")
    doctor = _sekd_in(ns, "doctor")
    assert doctor.returncode == 0 and f"{address} (what --ray-address auto joins)" in doctor.stdout, doctor.stdout


@pytest.fixture
def ray_tmpdir():
    """A private root for Ray's temporary files (``$RAY_TMPDIR``), so a test sees no other run's cluster files.

    Short (under /tmp): Ray's socket paths inside it must stay below the 107-byte limit of a unix socket.
    """
    folder = Path(tempfile.mkdtemp(prefix="sr", dir="/tmp"))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


@pytest.mark.parametrize("stale", [False, True], ids=["no-cluster-file", "stale-cluster-file"])
def test_auto_address_without_a_cluster_starts_a_local_one(tmp_path, ray_tmpdir, stale):
    """In a namespace where no cluster answers, ``auto`` starts a one-node cluster for the run and stops it after,
    leaving no ``~/.ray/auth_token`` behind (which would make every later ``ray start --head`` here require it).

    ``stale``: Ray's current-cluster file still names a cluster that was killed (nothing listens there); it is
    treated as no cluster (``ray.init()`` alone would try to join it and refuse to start one).
    """
    pytest.importorskip("ray", reason='ray is not installed (pip install "sekd-sfm[ray]")')
    if shutil.which("ip") is None:
        pytest.skip("ip (iproute2) not found")
    _installed("sekd")
    ns = f"sekdlocal{os.getpid()}"
    if _sh("ip", "netns", "add", ns).returncode != 0:
        pytest.skip("cannot create a network namespace (needs root)")
    if stale:
        (ray_tmpdir / "ray").mkdir()
        (ray_tmpdir / "ray" / "ray_current_cluster").write_text(f"127.0.0.1:{_closed_port()}")
    try:
        _sh("ip", "netns", "exec", ns, "ip", "link", "set", "lo", "up")
        token = Path.home() / ".ray" / "auth_token"
        had_token = token.exists()
        images = _photos(tmp_path / "images", 2)
        run = _sekd_in(ns, "extract", str(images), "-o", str(tmp_path / "f.h5"), "--resize-max", "160",
                       "--max-keypoints", "100", "--no-progress", "--executor", "ray",
                       env={"RAY_TMPDIR": str(ray_tmpdir), "SEKD_DEBUG": "1"})
        assert run.returncode == 0, run.stderr[-2000:]
        assert re.search(r"Ray: started a local cluster for this run \(1 node, \d+ CPUs?\)", run.stderr), run.stderr
        if stale:  # said only in the debug log
            assert "does not answer from here (127.0.0.1:" in run.stderr
        assert len({name.split("/")[0] for name in _contents(tmp_path / "f.h5")}) == 2
        deadline = time.monotonic() + 10
        while _namespace_pids(ns) and time.monotonic() < deadline:  # the driver stops what it started
            time.sleep(0.5)
        assert not _namespace_pids(ns)
        assert token.exists() == had_token
    finally:
        _stop_namespace(ns, tmp_path / "none")


def test_unreachable_ray_address_variable_is_one_error_line(tmp_path, monkeypatch):
    pytest.importorskip("ray", reason='ray is not installed (pip install "sekd-sfm[ray]")')
    images = _photos(tmp_path / "images", 1)
    address = f"127.0.0.1:{_closed_port()}"
    monkeypatch.setenv("RAY_ADDRESS", address)
    result = CliRunner().invoke(sekd, ["extract", str(images), "-o", str(tmp_path / "f.h5"), "--executor", "ray"])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert lines[-1].startswith(f"Error: no Ray cluster answers at {address} (from $RAY_ADDRESS) ("), lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images"]  # refused before anything was written


def test_ray_start_up_notes_go_to_the_debug_log(capfd, caplog):
    """What Ray's C++ core writes to file descriptor 2 while connecting is logged at debug level, not shown."""
    import logging

    from sekd_sfm.execution.ray_connect import _stderr_to_log

    with caplog.at_level(logging.DEBUG, logger="sekd"), _stderr_to_log():
        os.write(2, b"[W network_util.cc:330] Failed to determine local IP\n")
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "after\n"
    assert "Failed to determine local IP" in caplog.text


#: The hierarchical mapper in clusters of 3 photos (+2 shared): 5 photos give two clusters, mapped on two workers.
SMALL_CLUSTERS = ("--mapper-type", "hierarchical", "--mapper", "clustering_options.leaf_max_num_images=3",
                  "--mapper", "clustering_options.image_overlap=2", "--mapper", "incremental_options.min_model_size=3")


def test_reconstruct_on_ray(cluster, tmp_path):
    """``sekd reconstruct --executor ray``: every per-item stage on the cluster (extraction, matching, refinement,
    verification, the hierarchical mapper's clusters); 5 fountain-P11 photos at 640 px all registered, and the
    files and the model those of a local run."""
    fountain = SHARED / "data/sfm/fountain-P11/images"
    if not fountain.is_dir():
        pytest.skip(f"shared data not found at {fountain}")
    images = tmp_path / "images"
    images.mkdir()
    for src in sorted(fountain.iterdir())[:5]:
        (images / src.name).symlink_to(src)
    out = tmp_path / "out"
    run = _run_watching_actors(cluster[0], _ray_cli(cluster, "reconstruct", str(images), "-o", str(out),
                                                    "--resize-max", "640", "--no-progress", *SMALL_CLUSTERS))
    assert run.returncode == 0, run.stderr[-3000:]
    # The run's actors serve every stage: two CPUs, two actor processes for the whole run (not two per stage).
    assert 1 <= len(run.actors) <= 2, run.actors
    assert re.search(r"Ray: 5 imgs in ", run.stderr), run.stderr[-2000:]
    assert re.search(r"Ray: 10 pairs in ", run.stderr), run.stderr[-2000:]
    assert run.stderr.count("Ray: connected to the cluster") == 1  # one connection for both stages
    assert re.search(r"Ray: 10 pairs in ", run.stderr.split("refine keypoints")[-1]), run.stderr[-2000:]
    stats = json.loads((out / "stats.json").read_text())
    assert stats["status"] == "ok" and stats["model"]["registered_images"] == 5
    places = {row["stage"]: row["ran_on"] for row in stats["stages"]}
    assert all(places[stage].startswith("Ray: ") for stage in ("extract", "match", "refine", "verification",
                                                                "mapping"))
    assert re.search(r"Ray: 2 clusters in ", run.stderr), run.stderr[-2000:]
    local = extract_features(images, tmp_path / "local.h5", FeatureConfig(resize_max=640), progress=False,
                             num_threads=1)
    assert _contents(out / "features.h5") == _contents(local)
    # The same run here gives the same refined keypoints and verified pairs (features and matches reused).
    here = tmp_path / "here"
    here.mkdir()
    for name in ("features.h5", "matches.h5"):
        shutil.copy(out / name, here / name)
    result = CliRunner().invoke(sekd, ["reconstruct", str(images), "-o", str(here), "--resize-max", "640",
                                       "--no-progress", *SMALL_CLUSTERS])
    assert result.exit_code == 0, result.output[-2000:]
    assert _contents(out / "features-refined.h5") == _contents(here / "features-refined.h5")
    assert _verified(out / "database.db") == _verified(here / "database.db")
    # The same clusters, the same merge: the same cameras.
    import pycolmap

    ray_model, local_model = (pycolmap.Reconstruction(str(folder / "model")) for folder in (out, here))
    poses = [{m.image(i).name: m.image(i).cam_from_world().matrix() for i in m.reg_image_ids()}
             for m in (ray_model, local_model)]
    assert poses[0].keys() == poses[1].keys() and all(np.allclose(poses[0][k], poses[1][k], atol=1e-6)
                                                       for k in poses[0])


def _run_watching_actors(ns: str, command: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
    """Run ``command``; the result's ``actors``: the PIDs of every ``_RunActor`` process the namespace had meanwhile
    (looked at every 0.1 s)."""
    seen: set[int] = set()
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        driver = subprocess.Popen(command, stdout=out, stderr=err)
        deadline = time.monotonic() + timeout
        while driver.poll() is None:
            seen.update(_map_workers(ns))
            if time.monotonic() > deadline:
                driver.kill()
                break
            time.sleep(0.1)
        driver.wait()
        out.seek(0)
        err.seek(0)
        run = subprocess.CompletedProcess(command, driver.returncode, out.read().decode(errors="replace"),
                                          err.read().decode(errors="replace"))
    run.actors = seen
    return run


def _verified(database: Path) -> list:
    """Every pair's two-view geometry row of a COLMAP database (inliers, config, matrices), by pair id."""
    with contextlib.closing(sqlite3.connect(database)) as db:
        return db.execute("SELECT pair_id, rows, data, config, F, E, H FROM two_view_geometries ORDER BY pair_id").fetchall()


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


def test_workers_send_back_only_keys(local_run, tmp_path):
    """A task's arrays go to a chunk of ``<output>.parts/`` (shared storage); the driver gets ~100 B per item."""
    import torch

    from sekd_sfm.execution.ray_run import _StageActor
    from sekd_sfm.features import build_extractor
    from sekd_sfm.files import features as ff
    from sekd_sfm.files import matches as mf
    from sekd_sfm.files import partstore
    from sekd_sfm.stages.extract import ExtractWorker, describe_config, worker_config
    from sekd_sfm.stages.match import (
        MatchConfig,
        MatchWorker,
        batches,
        check_feature_file,
    )
    from sekd_sfm.stages.match import describe_config as describe_match
    from sekd_sfm.stages.pairs import read_pairs

    images, features, pairs, matches = local_run
    config, threads = FeatureConfig(resize_max=160, max_keypoints=300), torch.get_num_threads()
    try:  # actors are plain classes: called here in-process, as Ray would call them
        extractor, info = build_extractor(config)
        out = tmp_path / "features.h5"
        args = (str(images), worker_config(config, extractor), describe_config(config, extractor, info))
        worker = _StageActor(ExtractWorker, args, 1, str(out), ff.write_image_group)
        keys = sorted(p.name for p in images.iterdir())  # 5 photos and broken.jpg
        back = worker({"key": np.array(keys, dtype=object), "batch": np.arange(len(keys))})

        fattrs, sizes = check_feature_file(features)
        match_config = MatchConfig()
        groups = list(batches(read_pairs(pairs), sizes, match_config.max_elements))
        match_out = tmp_path / "matches.h5"
        args = (str(features), False, describe_match(match_config, str(fattrs["feature_type"]), False), match_config)
        matcher = _StageActor(MatchWorker, args, 1, str(match_out), mf.write_pair_group, joinable=False)
        pair_keys = [mf.pair_key(a, b) for group in groups for a, b in group]
        numbers = [number for number, group in enumerate(groups) for _ in group]  # the batches: one matrix each
        match_back = matcher({"key": np.array(pair_keys, dtype=object), "batch": np.array(numbers)})
    finally:
        torch.set_num_threads(threads)

    assert sorted(back) == ["chunk", "error", "fatal", "key", "meta"]  # no arrays come back
    assert list(back["key"]) == keys and not back["fatal"].any() and not any(back["meta"])  # meta: shards only
    assert [bool(e) for e in back["error"]] == [k == "broken.jpg" for k in keys]
    chunks = sorted(partstore.PartStore(out).root.glob("*.npz"))
    assert [c.name for c in chunks] == sorted({c for c in back["chunk"] if c})  # one chunk per task, on disk
    saved = partstore.PartStore(out).load_all()
    assert sorted(saved) == [k for k in keys if k != "broken.jpg"]
    for key, arrays in saved.items():  # bit for bit what the local run wrote
        local = ff.read_features(features, key)
        for name in ("keypoints", "descriptors", "scores", "image_size"):
            assert arrays[name].dtype == local[name].dtype and arrays[name].tobytes() == local[name].tobytes()
    sent = len(pickle.dumps(back))
    assert sent < 400 * len(keys)  # keys, errors, chunk names: the error line is the longest
    assert sum(a.nbytes for arrays in saved.values() for a in arrays.values()) > 100 * sent

    assert sorted(match_back) == ["chunk", "error", "fatal", "key", "meta"] and len(match_back["key"]) == 10
    assert len(pickle.dumps(match_back)) < 200 * 10
    with h5py.File(matches, "r") as f:
        for key, arrays in partstore.PartStore(match_out).load_all().items():
            group = f["/".join(json.loads(key))]
            for name, value in arrays.items():
                assert value.tobytes() == group[name][()].tobytes()


def test_unwritable_part_store_is_a_fatal_error(local_run, tmp_path):
    """A node that cannot write the output's folder stops the run with one error naming the folder and the node."""
    from sekd_sfm.execution.ray_run import _TaskParts

    blocker = tmp_path / "file"
    blocker.write_text("")
    chunk, problem = _TaskParts(str(blocker / "features.h5")).write([("a.jpg", {"scores": np.zeros(3, np.float32)})])
    assert chunk == "" and problem.startswith(f"{blocker}/features.h5.parts: the Ray worker on ")
    assert "shared storage at the same path on every node" in problem
    assert _TaskParts(str(tmp_path / "f.h5")).write([]) == ("", "")  # a task whose images all failed: no chunk


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
    from sekd_sfm.execution import RayOptions
    from sekd_sfm.execution.ray_pool import _workers

    assert _workers(_FakeRay(**resources), RayOptions(**options)) == expected


@pytest.mark.parametrize(("base", "workers", "expected"), [
    (4, 1, 4), (4, 32, 4), (4, 33, 5), (4, 64, 8), (4, 512, 64), (1, 2, 1), (1, 64, 2), (1, 512, 16),
])
def test_tasks_grow_with_the_cluster(base, workers, expected):
    """The driver's cost is per task: beyond 32 workers, tasks grow so it receives as many tasks per second as at 32."""
    from sekd_sfm.execution import task_size

    assert task_size(base, workers) == expected


@pytest.mark.parametrize(("resources", "options", "message"), [
    ({"CPU": 2.0}, {"threads_per_worker": 4}, "--threads-per-worker 4 but the Ray cluster has 2 CPUs"),
    ({"CPU": 2.0}, {"gpus_per_worker": 1}, "--gpus-per-worker 1 but the Ray cluster has 0 GPUs"),
])
def test_worker_size_larger_than_the_cluster_is_refused(resources, options, message):
    from sekd_sfm.errors import SekdError
    from sekd_sfm.execution import RayOptions
    from sekd_sfm.execution.ray_pool import _workers

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


def test_worker_skips_the_images_the_driver_claimed(local_run, tmp_path):
    """While workers start, the driver extracts from the end of the list; a worker skips those keys."""
    import torch

    from sekd_sfm.execution.ray_run import BY_DRIVER, _claims_path, _StageActor
    from sekd_sfm.features import build_extractor
    from sekd_sfm.stages.extract import ExtractWorker, describe_config, worker_config

    images, _, _, _ = local_run
    config, threads = FeatureConfig(resize_max=160, max_keypoints=300), torch.get_num_threads()
    out = tmp_path / "features.h5"
    claims = _claims_path(out)
    keys = sorted(p.name for p in images.iterdir() if p.name != "broken.jpg")
    claims.write_text(f"{keys[-1]}\n{keys[-2]}\n")
    try:
        extractor, info = build_extractor(config)
        args = (str(images), worker_config(config, extractor), describe_config(config, extractor, info))
        worker = _StageActor(ExtractWorker, args, 1, str(out), None, "copy", str(claims))
        back = worker({"key": np.array(keys, dtype=object), "batch": np.arange(len(keys))})
    finally:
        torch.set_num_threads(threads)
    by_key = dict(zip(back["key"], back["chunk"]))
    assert sorted(by_key) == keys and not any(back["error"])
    assert [k for k, c in by_key.items() if c == BY_DRIVER] == sorted(keys[-2:])  # counted by the driver, not here
    assert claims.name.startswith("features.h5.claims-") and claims.name.endswith(f".{os.getpid()}.tmp")


class _FakeNodes:
    """The two calls ``cluster._free_cores_here`` makes of Ray: the driver's IP and the node table."""

    def __init__(self, here: str, nodes: list[tuple[str, float, bool]]):
        self.util = type("util", (), {"get_node_ip_address": staticmethod(lambda: here)})
        self.table = [{"NodeManagerAddress": ip, "Resources": {"CPU": cpus}, "Alive": alive} for ip, cpus, alive in nodes]

    def nodes(self):
        return self.table


@pytest.mark.parametrize(("nodes", "options", "helps"), [
    ([("127.0.0.1", 1.0, True), ("127.0.0.1", 1.0, True)], {}, False),  # a one-machine cluster holds both cores
    ([("127.0.0.1", 1.0, True)], {}, True),  # one core left to the driver
    ([("127.0.0.1", 1.0, True)], {"threads_per_worker": 2}, False),  # not a worker's worth
    ([("10.0.0.5", 8.0, True)], {}, True),  # the driver's machine runs no Ray node (a login node)
    ([("127.0.0.1", 2.0, False), ("10.0.0.5", 8.0, True)], {}, True),  # a dead node here holds nothing
    ([("127.0.0.1", 2.0, True)], {"driver_helps": True}, True),  # forced
    ([("10.0.0.5", 8.0, True)], {"driver_helps": False}, False),  # off
    ([("10.0.0.5", 8.0, True)], {"gpus_per_worker": 1.0}, False),  # GPU workers compute otherwise
])
def test_driver_helps_only_with_cores_ray_does_not_hold(monkeypatch, nodes, options, helps):
    from sekd_sfm.execution import RayOptions
    from sekd_sfm.execution.ray_run import _driver_should_help

    monkeypatch.setattr("sekd_sfm.runtime.usable_cores", lambda: 2)
    assert _driver_should_help(_FakeNodes("127.0.0.1", nodes), RayOptions(**options)) is helps


@pytest.mark.parametrize(("nodes", "options", "merges"), [
    ([("127.0.0.1", 1.0, True), ("127.0.0.1", 1.0, True)], {}, False),  # a one-machine cluster holds both cores
    ([("10.0.0.5", 8.0, True)], {}, True),  # a login node: its cores copy while the workers compute
    ([("127.0.0.1", 1.0, True)], {}, True),  # one core left to the driver
    ([("10.0.0.5", 8.0, True)], {"merge": "virtual"}, False),  # nothing to copy
    ([("127.0.0.1", 2.0, True)], {"merge_while_running": True}, True),  # forced
    ([("10.0.0.5", 8.0, True)], {"merge_while_running": False}, False),  # off
])
def test_driver_merges_while_running_only_with_cores_ray_does_not_hold(monkeypatch, nodes, options, merges):
    from sekd_sfm.execution import RayOptions
    from sekd_sfm.execution.ray_connect import _merges_while_running

    monkeypatch.setattr("sekd_sfm.runtime.usable_cores", lambda: 2)
    assert _merges_while_running(_FakeNodes("127.0.0.1", nodes), RayOptions(**options)) is merges


def test_merge_while_running_gives_the_same_file(cluster, local_run, tmp_path):
    """The driver copying each task's chunk as it arrives (forced on: this cluster holds every core) changes nothing."""
    images, features, _, _ = local_run
    out = tmp_path / "features.h5"
    run = subprocess.run(_library_extract(cluster, images, out, "resize_max=160, max_keypoints=300",
                                          "images_per_task=1, merge_while_running=True"),
                         check=False, capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "the driver copies the workers' results into the output as they arrive" in run.stderr
    copied = re.findall(r"Ray: (\d+) of the 6 imgs were in the output's copy when the workers finished", run.stderr)
    assert copied and 1 <= int(copied[-1]) <= 5, run.stderr[-2000:]  # 5 photos + broken.jpg (never copied)
    assert _contents(out) == _contents(features)
    assert _attrs(out) == _attrs(features)
    assert not list(tmp_path.glob("*.tmp")) and not Path(f"{out}.parts").exists()


class _ScriptedPool:
    """Stand-in for Ray in ``cluster._pool_results``: actors whose calls end as a script says.

    Each ``wait`` plays the next event: ``("done", i)`` finishes actor i's oldest call;
    ``("die", i)`` fails every call actor i holds (as Ray does when its process dies);
    ``("back", i)`` / ``("lost", i)``: its ``__ray_ready__`` answers (up) / fails (still
    restarting); while actor i has not been asked yet, the wait times out with nothing ready.
    Records the keys each actor was given, and the most calls one held at once.
    """

    def __init__(self, actors: int, events: list[tuple[str, int]]):
        self.events = list(events)
        self.calls: list[list[object]] = [[] for _ in range(actors)]  # refs each actor holds
        self.probes: dict[int, object] = {}
        self.batches: dict[object, str] = {}
        self.failed: set[object] = set()
        self.given: list[list[str]] = [[] for _ in range(actors)]
        self.most_queued = 0
        self.actors = [self._actor(i) for i in range(actors)]

    def _actor(self, index: int):
        pool = self

        class Call:
            @staticmethod
            def remote(batch):
                ref = object()
                pool.batches[ref] = ",".join(batch["key"])
                pool.given[index].append(pool.batches[ref])
                pool.calls[index].append(ref)
                pool.most_queued = max(pool.most_queued, len(pool.calls[index]))
                return ref

        class Ready:
            @staticmethod
            def remote():
                pool.probes[index] = object()
                return pool.probes[index]

        return type("Actor", (), {"__call__": Call, "__ray_ready__": Ready})()

    def wait(self, refs, num_returns=1, timeout=None):
        what, index = self.events[0]
        if what in ("back", "lost") and index not in self.probes:
            return [], refs  # not asked yet: nothing happens within the timeout
        self.events.pop(0)
        if what == "done":
            ready = [self.calls[index].pop(0)]
        elif what == "die":
            ready, self.calls[index] = self.calls[index], []
            self.failed.update(ready)
        else:
            ready = [self.probes.pop(index)]
            if what == "lost":
                self.failed.update(ready)
        assert all(ref in refs for ref in ready)
        return ready, [r for r in refs if r not in ready]

    def get(self, ref):
        from ray.exceptions import ActorDiedError

        if ref in self.failed:
            raise ActorDiedError()
        return {"key": self.batches[ref]} if ref in self.batches else None  # None: a __ray_ready__ answer


def _tasks(count: int, size: int) -> list[dict]:
    from sekd_sfm.execution.ray_pool import _columns

    items = [{"key": f"img{i}.jpg"} for i in range(count)]
    return [_columns(items[i:i + size]) for i in range(0, count, size)]


def test_actor_pool_gives_each_task_once_and_the_next_to_whoever_finishes():
    pytest.importorskip("ray", reason='ray is not installed (pip install "sekd-sfm[ray]")')
    from sekd_sfm.execution.ray_pool import TASKS_IN_FLIGHT, _pool_results

    tasks = _tasks(9, 2)  # 4 tasks of 2 and one of 1
    assert list(tasks[0]["key"]) == ["img0.jpg", "img1.jpg"] and tasks[0]["key"].dtype == object
    # Both actors start; actor 0 finishes everything it holds, actor 1 is stuck on its first call until the end.
    pool = _ScriptedPool(2, [("back", 0), ("back", 1), ("done", 0), ("done", 0), ("done", 0), ("done", 1), ("done", 1)])
    results = [r["key"] for r in _pool_results(pool, pool.actors, tasks)]
    assert TASKS_IN_FLIGHT == 2 and pool.most_queued == 2
    # Two tasks to each actor as it comes up; the last one to actor 0, free first.
    assert pool.given == [["img0.jpg,img1.jpg", "img2.jpg,img3.jpg", "img8.jpg"], ["img4.jpg,img5.jpg", "img6.jpg,img7.jpg"]]
    assert results[:3] == ["img0.jpg,img1.jpg", "img2.jpg,img3.jpg", "img8.jpg"]  # in the order they finished
    assert sorted(results) == sorted(",".join(t["key"]) for t in tasks)


def test_actor_pool_with_more_actors_than_tasks():
    pytest.importorskip("ray", reason='ray is not installed (pip install "sekd-sfm[ray]")')
    from sekd_sfm.execution.ray_pool import _pool_results

    pool = _ScriptedPool(3, [("back", 0), ("done", 0)])  # actors 1 and 2 never come up: no task waits for them
    assert [r["key"] for r in _pool_results(pool, pool.actors, _tasks(1, 4))] == ["img0.jpg"]
    assert pool.given == [["img0.jpg"], [], []]
    assert list(_pool_results(pool, pool.actors, [])) == []


def test_actor_pool_gives_few_tasks_one_per_actor():
    """Two long tasks (a mapping's clusters) on two actors: the first actor up takes one, not both."""
    pytest.importorskip("ray", reason='ray is not installed (pip install "sekd-sfm[ray]")')
    from sekd_sfm.execution.ray_pool import _pool_results

    pool = _ScriptedPool(2, [("back", 0), ("back", 1), ("done", 1), ("done", 0)])
    results = [r["key"] for r in _pool_results(pool, pool.actors, _tasks(2, 1))]
    assert pool.given == [["img0.jpg"], ["img1.jpg"]] and pool.most_queued == 1
    assert results == ["img1.jpg", "img0.jpg"]


def test_actor_pool_gives_a_dead_workers_tasks_to_the_others_then_takes_it_back(monkeypatch):
    pytest.importorskip("ray", reason='ray is not installed (pip install "sekd-sfm[ray]")')
    from sekd_sfm.execution import ray_pool as cluster
    from sekd_sfm.execution.ray_pool import _pool_results

    monkeypatch.setattr(cluster, "REPROBE_SECONDS", 0.0)

    lost = []
    pool = _ScriptedPool(2, [("back", 0), ("back", 1), ("die", 1), ("done", 0), ("done", 0), ("back", 1),
                             ("done", 0), ("done", 1), ("done", 0), ("done", 1)])
    results = [r["key"] for r in _pool_results(pool, pool.actors, _tasks(6, 1), lost.append)]
    assert sorted(results) == [f"img{i}.jpg" for i in range(6)]  # every task done once
    assert len(lost) == 1  # one warning for the actor, though it held two tasks
    # Actor 1 held img2 and img3 when it died: they went to the front of the queue, in order, and
    # actor 0 took them; once restarted, actor 1 took the next two.
    assert pool.given == [["img0.jpg", "img1.jpg", "img2.jpg", "img3.jpg"], ["img2.jpg", "img3.jpg", "img4.jpg", "img5.jpg"]]


def test_actor_pool_waits_for_its_only_worker_to_come_back(monkeypatch, caplog):
    pytest.importorskip("ray", reason='ray is not installed (pip install "sekd-sfm[ray]")')
    from sekd_sfm.execution import ray_pool as cluster

    monkeypatch.setattr(cluster, "REPROBE_SECONDS", 0.0)
    pool = _ScriptedPool(1, [("back", 0), ("done", 0), ("die", 0), ("lost", 0), ("lost", 0), ("back", 0),
                             ("done", 0), ("done", 0), ("done", 0), ("done", 0)])
    with caplog.at_level("WARNING", logger="sekd"):
        results = [r["key"] for r in cluster._pool_results(pool, pool.actors, _tasks(5, 1))]
    assert sorted(results) == [f"img{i}.jpg" for i in range(5)]
    # It held img1 and img2 when it died; back after two asks, it takes them again, then the rest.
    assert pool.given == [["img0.jpg", "img1.jpg", "img2.jpg", "img1.jpg", "img2.jpg", "img3.jpg", "img4.jpg"]]
    assert [r.getMessage() for r in caplog.records].count(
        "no Ray worker is up: waiting for the cluster to start or restart them (Ctrl-C keeps every finished item)") == 1
