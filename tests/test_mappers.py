"""The three pycolmap mappers, their option checks, the mapper's child process and Ctrl-C."""
import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from click.testing import CliRunner
from test_reconstruct import (
    CALIBRATED,
    SIFT,
    arc,
    scene_points,
    synthetic_views,
    write_scene,
)

from sekd_sfm.cli.main import sekd
from sekd_sfm.errors import SekdError
from sekd_sfm.pipelines.reconstruct import ReconstructConfig, reconstruct
from sekd_sfm.stages.colmap import require_pycolmap
from sekd_sfm.stages.mapping import (
    MAPPER_TYPES,
    default_options,
    mapper_options,
    resolve_mapper_type,
    run_mapper,
)

pycolmap = require_pycolmap()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Twelve calibrated views on a 100 degree arc; features and matches made once, by the incremental run."""
    rng = np.random.default_rng(21)
    points, descriptors = scene_points(rng, 400)
    views = {f"v{i:02d}.png": v for i, v in enumerate(synthetic_views(rng, points, descriptors, arc(12, span_deg=100)))}
    images, out = write_scene(tmp_path_factory.mktemp("mappers"), views, SIFT)
    reconstruct(images, out, ReconstructConfig(features=SIFT, camera=CALIBRATED), progress=False)
    return images, out


@pytest.mark.parametrize("mapper_type", MAPPER_TYPES)
def test_each_mapper_registers_every_view(scene, tmp_path, mapper_type):
    images, first = scene
    out = tmp_path / "out"
    out.mkdir()
    for name in ("features.h5", "pairs.txt", "matches.h5"):
        (out / name).write_bytes((first / name).read_bytes())
    # The hierarchical mapper keeps clusters of >= 10 images by default; this scene has 12.
    config = ReconstructConfig(features=SIFT, camera=CALIBRATED, mapper_type=mapper_type)
    model = reconstruct(images, out, config, progress=False)
    stats = json.loads((out / "stats.json").read_text())
    assert stats["status"] == "ok" and stats["config"]["mapper_type"] == mapper_type
    assert stats["model"]["registered_images"] == 12 and stats["model"]["points3D"] > 300
    assert stats["model"]["mean_reprojection_error_px"] < 1.0 and stats["unregistered"] == []
    assert pycolmap.Reconstruction(str(model)).num_reg_images() == 12
    log = (out / "colmap.log").read_text()
    assert "Elapsed time" in log and not list(out.glob("mapping-*")) and not list(out.glob("colmap.log.*"))


def test_default_options_are_seeded_and_single_threaded():
    assert default_options("incremental", 4).random_seed == 4
    assert default_options("global", 4).random_seed == 4 and default_options("global").num_threads == 1
    hierarchical = default_options("hierarchical", 4)
    assert hierarchical.incremental_options.random_seed == 4 and hierarchical.num_threads == 1
    with pytest.raises(SekdError, match="unknown mapper type 'glomap'; choose from incremental, global, hierarchical"):
        default_options("glomap")


@pytest.mark.parametrize("mapper_type,assignment,message", [
    ("global", "mapper.init_min_tri_angle=8",
     r"--mapper mapper.init_min_tri_angle: no such option in pycolmap's GlobalPipelineOptions"),
    ("incremental", "mapper.rotation_averaging.max_rotation_error_deg=5", "IncrementalPipelineOptions"),
    ("hierarchical", "min_num_matches=30",
     r"HierarchicalPipelineOptions; did you mean .*incremental_options.min_num_matches"),
])
def test_option_of_another_mapper_is_one_error_before_any_work(tmp_path, mapper_type, assignment, message):
    (tmp_path / "images").mkdir()
    result = CliRunner().invoke(sekd, ["-q", "reconstruct", str(tmp_path / "images"), "-o", str(tmp_path / "out"),
                                       "--mapper-type", mapper_type, "--mapper", assignment])
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert result.exit_code == 1 and len(errors) == 1, result.output
    assert re.search(message, errors[0]), errors[0]
    assert not (tmp_path / "out" / "features.h5").exists()


def test_options_of_each_mapper_are_accepted():
    assert mapper_options(["mapper.rotation_averaging.max_rotation_error_deg=5"], mapper_type="global") \
        .mapper.rotation_averaging.max_rotation_error_deg == 5
    assert mapper_options(["incremental_options.min_num_matches=30", "num_workers=2"], mapper_type="hierarchical") \
        .incremental_options.min_num_matches == 30


@pytest.mark.parametrize("mapper_type,expected", [("global", "mapper.rotation_averaging.max_rotation_error_deg = 10.0"),
                                                  ("hierarchical", "clustering_options.leaf_max_num_images = 125"),
                                                  ("auto", "# --mapper-type auto: these options up to 250 photos")])
def test_mapper_help_lists_the_options_of_the_chosen_type(mapper_type, expected):
    result = CliRunner().invoke(sekd, ["reconstruct", "x", "-o", "y", "--mapper", "help", "--mapper-type", mapper_type])
    assert result.exit_code == 0 and expected in result.output
    assert "mapper.init_min_tri_angle" not in result.output or mapper_type in ("hierarchical", "auto")


def test_auto_maps_small_collections_incrementally_and_large_ones_hierarchically():
    assert resolve_mapper_type("auto", 10) == resolve_mapper_type("auto", 250) == "incremental"
    assert resolve_mapper_type("auto", 251) == "hierarchical"
    assert resolve_mapper_type("global", 10_000) == "global"
    with pytest.raises(SekdError, match="unknown mapper type 'fast'; choose from auto, incremental"):
        resolve_mapper_type("fast", 10)
    options = mapper_options(mapper_type="hierarchical")
    assert options.clustering_options.leaf_max_num_images == 125 and options.num_workers == 1
    assert options.incremental_options.num_threads == 1


# ----------------------------------------------------------------------------- Ctrl-C

# Start from a shell's signal state, whatever the test process passed on (a mask, an ignored SIGINT).
CLEAN_SIGNALS = ("import signal; signal.pthread_sigmask(signal.SIG_SETMASK, set()); "
                 "signal.signal(signal.SIGINT, signal.default_int_handler)\n")
HARNESS = textwrap.dedent("""
    import sys, time
    from sekd_sfm.errors import Interrupted
    from sekd_sfm.stages import mapping
    # A mapper that would run for a minute (the real ones look for Ctrl-C rarely or never).
    mapping.WORKER_COMMAND = [sys.executable, "-c", "import time; print(flush=True); time.sleep(60)"]
    try:
        mapping.run_mapper(sys.argv[1], sys.argv[2], progress=False)
    except Interrupted as exc:
        print("INTERRUPTED", time.time(), exc, flush=True)
""")


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_kills_the_mapper_at_once_and_leaves_nothing(tmp_path, signum):
    database = tmp_path / "database.db"
    pycolmap.Database.open(str(database)).close()
    # The CLI's SIGTERM policy (raise KeyboardInterrupt), as `sekd` installs it.
    script = CLEAN_SIGNALS + "from sekd_sfm.runtime import stop_cleanly_on_sigterm; stop_cleanly_on_sigterm()\n" + HARNESS
    child = subprocess.Popen([sys.executable, "-c", script, str(database), str(tmp_path)],
                             stdout=subprocess.PIPE, text=True)
    deadline = time.time() + 60
    while not list(tmp_path.glob("mapping-*/stderr.txt")) or not _worker_pids(child.pid):
        assert time.time() < deadline and child.poll() is None
        time.sleep(0.05)
    workers = _worker_pids(child.pid)
    sent = time.time()
    child.send_signal(signum)
    out, _ = child.communicate(timeout=30)
    stopped = float(out.split("INTERRUPTED ")[1].split()[0])
    assert stopped - sent < 2.0, out  # was 15-17 s with the mapper in-process
    assert "is kept; run the same command again to map again" in out
    assert not list(tmp_path.glob("mapping-*"))
    for pid in workers:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def _worker_pids(parent: int) -> list[int]:
    """PIDs of the fake mapper workers (``time.sleep(60)``) among the children of ``parent`` (from /proc)."""
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    is_child = int(f.read().rsplit(")", 1)[1].split()[1]) == parent
                with open(f"/proc/{entry}/cmdline", "rb") as f:
                    if is_child and b"time.sleep(60)" in f.read():
                        pids.append(int(entry))
            except (OSError, IndexError, ValueError):
                continue
    return pids


def test_a_failing_mapper_is_one_clear_error(tmp_path):
    database = tmp_path / "database.db"
    pycolmap.Database.open(str(database)).close()
    with pytest.raises(SekdError, match=r"the incremental mapper failed on .*database.db \(exit code 1\): .*"):
        run_mapper(database, tmp_path / "no such folder", progress=False)
    assert not list(tmp_path.glob("mapping-*"))



def test_poses_from_a_model_are_closed_over_the_database(scene, tmp_path):
    """``run_mapper(poses_from=...)``: no mapping; the model's poses held, its points triangulated again from the
    database and the whole adjusted: the same photos, the cameras where they were (how the capture order closes
    its chain). The global mapper's options cannot do it: one error, nothing left behind."""
    from sekd_sfm.stages.hierarchical import model_arrays

    images, first = scene
    model = pycolmap.Reconstruction(str(first / "model"))
    database = tmp_path / "database.db"
    database.write_bytes((first / "database.db").read_bytes())
    closed = run_mapper(database, images, mapper_options(), progress=False, poses_from=[model_arrays([model])])
    assert len(closed) == 1 and closed[0].num_reg_images() == 12 and closed[0].num_points3D() > 300
    for image_id in model.reg_image_ids():
        before, after = model.image(image_id).projection_center(), closed[0].image(image_id).projection_center()
        assert np.linalg.norm(before - after) < 1e-2 * np.linalg.norm(before)
    with pytest.raises(SekdError, match="poses_from needs incremental or hierarchical"):
        run_mapper(database, images, mapper_options(mapper_type="global"), progress=False,
                   poses_from=[model_arrays([model])])
    assert not list(tmp_path.glob("mapping-*"))


def test_the_mapper_dies_with_a_killed_parent(tmp_path):
    """kill -9 of `sekd` mid-mapping: the child must not map on alone (Linux parent-death signal)."""
    database = tmp_path / "database.db"
    pycolmap.Database.open(str(database)).close()
    worker = ("import os, time; from sekd_sfm.stages import mapper_worker as w; w._die_with_parent(os.getppid()); "
              "time.sleep(60)")
    script = HARNESS.replace('"import time; print(flush=True); time.sleep(60)"', repr(worker))
    parent = subprocess.Popen([sys.executable, "-c", script, str(database), str(tmp_path)])
    deadline = time.time() + 60
    while not _worker_pids(parent.pid):
        assert time.time() < deadline and parent.poll() is None
        time.sleep(0.05)
    (worker_pid,) = _worker_pids(parent.pid)
    time.sleep(1.0)  # let the child reach prctl
    parent.kill()
    parent.wait()
    deadline = time.time() + 5
    while _alive(worker_pid):
        assert time.time() < deadline, "the mapper outlived its killed parent"
        time.sleep(0.05)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False
