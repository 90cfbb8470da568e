"""The run object (``sekd_sfm.pipelines.run``) and the record (``sekd_sfm.pipelines.record``): one executor per run,
steps timed and skipped as declared, contexts held to the run's end, a step added to ``RECONSTRUCT`` in one line."""
from __future__ import annotations

import json
from contextlib import contextmanager

import pytest

from sekd_sfm.errors import SekdError
from sekd_sfm.pipelines import record
from sekd_sfm.pipelines import run as run_module
from sekd_sfm.pipelines.config import ReconstructConfig, config_dict
from sekd_sfm.pipelines.reconstruct import RECONSTRUCT, reconstruct
from sekd_sfm.pipelines.run import Run, RunOptions, Step, run_steps


def test_steps_run_in_order_timed_as_declared_and_skipped_when_told(tmp_path):
    seen: list[str] = []

    def step(name):
        def run(_run, state):
            seen.append(name)
            return [*state, name]
        return run

    steps = (Step("check", step("check"), timed=False), Step("a", step("a")),
             Step("skipped", step("skipped"), when=lambda state: False), Step("b", step("b"), when=lambda s: "a" in s))
    with Run(tmp_path / "out") as run:
        state = run_steps(run, steps, [])
    assert state == seen == ["check", "a", "b"]
    assert list(run.seconds) == ["a", "b"] and set(run.timings()) == {"a", "b", "total"}
    assert not (tmp_path / "out").exists()  # no lock asked for: the run makes no folder


def test_the_stage_table_says_where_each_step_computed(tmp_path):
    """A step that runs a stage on the executor is listed with the executor's place, the others as the driver's;
    the summary prints the table."""
    from sekd_sfm.pipelines.report import stage_lines

    def spread(run, state):
        run.executor.places.append("local: 2 processes")  # what LocalExecutor.run records for a spread stage
        return state

    steps = (Step("refine", spread), Step("mapping", lambda run, state: state))
    with Run(tmp_path, RunOptions(num_threads=2)) as run:
        run_steps(run, steps, None)
    table = run.stage_table()
    assert [(row["stage"], row["ran_on"]) for row in table] == [("refine", "local: 2 processes"), ("mapping", "driver")]
    lines = stage_lines({"stages": table, "timings_s": run.timings()})
    assert lines[0].split() == ["stages", "seconds", "ran", "on"] and lines[1].split()[0] == "refine"
    assert lines[1].endswith("local: 2 processes") and lines[2].endswith("driver") and lines[-1].split()[0] == "total"
    assert stage_lines({"timings_s": {"extract": 1.0, "total": 1.0}}) == ["  time               extract 1.0s, total 1.0s"]


def test_a_steps_timed_parts_add_up_under_it_in_the_table_and_the_summary(tmp_path):
    """``Run.part`` times parts of the running step (a part run twice adds up); outside a timed step it records
    nothing; the table and the summary list the parts under their step."""
    from sekd_sfm.pipelines.report import stage_lines

    def mapping(run, state):
        for name in ("clusters", "closing", "clusters"):
            with run.part(name):
                pass
        return state

    def untimed(run, state):
        with run.part("ignored"):
            return state

    with Run(tmp_path) as run:
        run_steps(run, (Step("options", untimed, timed=False), Step("mapping", mapping),
                        Step("check", lambda run, state: state)), None)
    table = run.stage_table()
    assert list(table[0]["parts"]) == ["clusters", "closing"] and "parts" not in table[1]
    assert sum(table[0]["parts"].values()) <= table[0]["seconds"] + 1e-3
    assert "ignored" not in json.dumps(table)
    lines = stage_lines({"stages": table, "timings_s": run.timings()})
    assert [line.split()[0] for line in lines] == ["stages", "mapping", "clusters", "closing", "check", "total"]
    assert lines[2].startswith("      clusters") and len(lines[2].split()) == 2  # indented, no place of its own


def test_one_executor_for_the_whole_run_closed_at_its_end(tmp_path, monkeypatch):
    opened: list[str] = []

    class Counting:
        name, virtual_merge, places = "local", False, []

        def __enter__(self):
            opened.append("enter")
            return self

        def __exit__(self, *exc):
            opened.append("exit")

    monkeypatch.setattr(run_module, "open_executor", lambda name, options, processes: Counting())
    executors = []
    steps = [Step(f"s{i}", lambda run, state: executors.append(run.executor) or state) for i in range(3)]
    with Run(tmp_path) as run:
        run_steps(run, steps, None)
        assert opened == ["enter"]
    assert opened == ["enter", "exit"] and len({id(e) for e in executors}) == 1
    with pytest.raises(RuntimeError):
        run.executor  # noqa: B018 - outside its block


def test_a_wrong_executor_fails_before_the_folder_is_made(tmp_path):
    with pytest.raises(SekdError, match="unknown executor"), Run(tmp_path / "out", RunOptions(executor="nope"),
                                                                  lock="reconstruction folder"):
        pass
    assert not (tmp_path / "out").exists()


def test_the_folder_lock_refuses_a_second_run(tmp_path):
    with Run(tmp_path / "out", lock="reconstruction folder"):
        with pytest.raises(SekdError), Run(tmp_path / "out", lock="reconstruction folder"):
            pass
    with Run(tmp_path / "out", lock="reconstruction folder"):  # released at the end of the first
        pass


def test_held_contexts_close_when_the_run_ends_also_on_failure(tmp_path):
    events: list[str] = []

    @contextmanager
    def held(name):
        events.append(f"open {name}")
        yield name
        events.append(f"close {name}")

    def opens(name):
        return lambda run, state: run.hold(held(name)) and state

    def fails(run, state):
        raise ValueError("a step failed")

    with pytest.raises(ValueError), Run(tmp_path) as run:
        run_steps(run, [Step("a", opens("log")), Step("b", opens("db")), Step("c", fails)], None)
    assert events == ["open log", "open db", "close db", "close log"]
    assert set(run.seconds) == {"a", "b", "c"}  # a failed step's time is recorded too


def test_record_round_trip_of_the_configuration(tmp_path):
    config = ReconstructConfig(mapper=["mapper.init_min_tri_angle=8"], seed=3, masks="/m")
    config.features.max_keypoints, config.refine.enabled, config.file_names = 3000, False, ("f.h5", "m.h5")
    record.write_record({"status": "ok", "config": config_dict(config), "images_dir": "photos",
                         "inputs": {"features": None, "matches": None}}, tmp_path)
    read = record.Record.from_record(tmp_path)
    back = read.config(weights="w.pth")
    assert isinstance(back, ReconstructConfig) and back.file_names == ("f.h5", "m.h5")
    assert config_dict(back) == config_dict(config) and back.features.weights == "w.pth"
    assert read.features == tmp_path / "f.h5" and read.refined == tmp_path / "f-refined.h5"
    assert read.masks == "/m" and read.images_dir == "photos" and not read.finished  # no model/ on disk


def test_a_record_before_the_final_filter_reads_without_it(tmp_path):
    data = config_dict(ReconstructConfig())
    data.pop("final_filter")
    (tmp_path / record.STATS).write_text(json.dumps({"status": "ok", "config": data}))
    assert record.Record.from_record(tmp_path).config().final_filter is False


def test_a_folder_without_a_record_is_one_clear_error(tmp_path):
    with pytest.raises(SekdError, match="not an output folder of `sekd reconstruct`"):
        record.Record.from_record(tmp_path)
    (tmp_path / record.STATS).write_text("{}")
    with pytest.raises(SekdError, match="no config.features"):
        record.Record.from_record(tmp_path)


def test_a_new_step_is_one_line_in_the_pipeline(tmp_path):
    """A step of one's own between matching and refinement sees the run's files and lands in the record."""
    from test_reconstruct import CALIBRATED, SIFT, write_arc_scene

    _, images, out = write_arc_scene(tmp_path)

    def count_matches(run, state):
        from sekd_sfm.files import matches as mf

        state.stats["my_step"] = {"pairs": len(mf.list_pairs(state.matches)), "executor": run.executor.name}
        return state

    at = [step.name for step in RECONSTRUCT].index("match") + 1
    steps = (*RECONSTRUCT[:at], Step("my step", count_matches), *RECONSTRUCT[at:])
    model = reconstruct(images, out, ReconstructConfig(features=SIFT, camera=CALIBRATED), progress=False, steps=steps)
    stats = record.read_record(out)
    assert model == out / record.MODEL and stats["status"] == "ok"
    assert stats["my_step"] == {"pairs": 28, "executor": "local"} and "my step" in stats["timings_s"]
