"""Wall time, peak memory and bytes written of a function run in a fresh process (Linux ``/proc``).

The function runs in a fresh Python process (nothing inherited from the parent's memory), while
the parent samples the child's resident set size (``VmRSS``) and the bytes it has passed
to ``write()`` (``wchar`` of ``/proc/PID/io``: files, pipes and sockets, before the page
cache) every ``interval`` seconds, with timestamps. The child adds its exact peak
(``VmHWM``) and final byte count when it returns. A stage inside the function (e.g. the
stages of ``reconstruct``) is measured by cutting this timeline at the stage boundaries.
"""
from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from ...errors import SekdError


def proc_status(pid: int | str = "self") -> dict[str, int]:
    """``VmRSS``/``VmHWM`` (bytes), ``wchar``/``write_bytes`` (bytes) and ``cpu`` (user + system s) of a process.

    Empty when the process is gone.
    """
    values: dict[str, int] = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                values[key] = int(rest.split()[0]) * 1024
        for line in Path(f"/proc/{pid}/io").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("wchar", "write_bytes"):
                values[key] = int(rest)
        # utime, stime, cutime, cstime (fields 14-17, after the parenthesised command name), in ticks:
        # all threads, plus the children already waited for (a worker process that has ended).
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
        values["cpu"] = sum(int(v) for v in fields[11:15]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        pass
    return values


def _children() -> dict[int, list[int]]:
    """Parent pid -> child pids of every process (from ``/proc/*/stat``)."""
    tree: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rpartition(")")[2].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        tree.setdefault(ppid, []).append(int(stat.parent.name))
    return tree


def tree_status(pid: int) -> dict[str, int]:
    """``proc_status`` summed over a process and its live descendants (worker processes, e.g. a mapper).

    ``cpu`` and ``wchar`` of ended children are already in their parent's figures (Linux adds
    a waited-for child's CPU time and I/O to its parent's), so the sums only grow.
    """
    total = proc_status(pid)
    if not total:
        return total
    tree = _children()
    stack = list(tree.get(pid, []))
    while stack:
        child = stack.pop()
        stack += tree.get(child, [])
        for key, value in proc_status(child).items():
            if key != "VmHWM":
                total[key] = total.get(key, 0) + value
    return total


@dataclass
class Measurement:
    """One measured call: wall time (s), peak RSS and bytes written, the samples, and what it returned."""

    wall_s: float
    peak_rss: int
    bytes_written: int
    cpu_s: float = 0.0   # user + system CPU seconds of all its threads
    samples: list[tuple[float, int, int, float]] = field(default_factory=list)  # (unix time, rss, wchar, cpu s)
    start: float = 0.0   # unix time when the function was entered (after the child's imports)
    result: object = None
    error: str | None = None

    def window(self, begin: float, end: float) -> dict:
        """Peak RSS and bytes written between two unix times (from the samples)."""
        inside = [s for s in self.samples if begin <= s[0] <= end]
        before = [s for s in self.samples if s[0] < begin]
        written0 = before[-1][2] if before else (inside[0][2] if inside else 0)
        written1 = inside[-1][2] if inside else written0
        # A stage shorter than the sampling interval has no sample of its own: the RSS at its start stands in.
        rss = [s[1] for s in inside] or [s[1] for s in before[-1:]]
        cpu0 = before[-1][3] if before else (inside[0][3] if inside else 0.0)
        cpu1 = inside[-1][3] if inside else cpu0
        return {"peak_rss": max(rss, default=0), "bytes_written": max(0, written1 - written0),
                "cpu_s": max(0.0, cpu1 - cpu0)}


def _child(task: str, report: str) -> None:
    """Body of the measured process: unpickle ``(target, args)``, run it, write the answer as JSON."""
    start = time.time()
    output: dict = {"start": start}
    try:
        with open(task, "rb") as f:
            target, args = pickle.load(f)
        output["start"] = start = time.time()  # after unpickling, which imports the target's module
        output["result"] = target(*args)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which decides
        output["error"] = "".join(traceback.format_exception_only(type(exc), exc)).strip().splitlines()[-1]
        output["traceback"] = traceback.format_exc()
    output["end"] = time.time()
    output["status"] = proc_status()
    Path(report).write_text(json.dumps(output, default=str))


def run_measured(target, args: tuple, report: str | Path, interval: float = 0.2) -> Measurement:
    """Run ``target(*args)`` (a module-level function, JSON-serialisable result) in a spawned process.

    ``report`` is a JSON file for the child's answer, to which the samples (unix time, RSS,
    bytes written, CPU s) are added at the end. Raises SekdError when the
    child dies without answering (killed, out of memory); an exception inside ``target``
    is returned as ``Measurement.error`` with the samples taken so far.
    """
    report = Path(report)
    report.unlink(missing_ok=True)
    task, log = report.with_suffix(".task"), report.with_suffix(".log")
    task.write_bytes(pickle.dumps((target, args)))
    begin = time.time()
    # A fresh interpreter (not fork, not multiprocessing's spawn, which re-imports the caller's
    # __main__ and so the whole CLI) holds only what the measured function itself imports.
    with open(log, "wb") as stream:
        process = subprocess.Popen([sys.executable, "-m", __name__, str(task), str(report)],
                                   stdout=stream, stderr=subprocess.STDOUT)
        samples = []
        try:
            while process.poll() is None:
                status = tree_status(process.pid)
                if "VmRSS" in status:
                    samples.append((time.time(), status["VmRSS"], status.get("wchar", 0), status.get("cpu", 0.0)))
                try:
                    process.wait(interval)
                except subprocess.TimeoutExpired:
                    pass
        finally:  # interrupted (Ctrl-C, SIGTERM): the measured process must not outlive us
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(10)
                except subprocess.TimeoutExpired:
                    process.kill()
    wall = time.time() - begin
    if not report.is_file():
        raise SekdError(f"the measured process ended with exit code {process.returncode} and no report "
                        f"({getattr(target, '__name__', target)}); it may have run out of memory; see {log}")
    output = json.loads(report.read_text())
    final = output.get("status", {})
    if final:
        samples.append((output["end"], final.get("VmRSS", 0), final.get("wchar", 0), final.get("cpu", 0.0)))
    # The samples stay with the report, so a stage's peak can be traced to its moment afterwards.
    output["samples"] = [[round(t, 2), rss, written, round(cpu, 2)] for t, rss, written, cpu in samples]
    report.write_text(json.dumps(output, default=str))
    peak = max([final.get("VmHWM", 0)] + [s[1] for s in samples])
    written = final.get("wchar", samples[-1][2] if samples else 0)
    # CPU from the function's start: what the interpreter and the unpickling (imports) used before is left out.
    before = [s_[3] for s_ in samples if s_[0] < output["start"]]
    cpu = final.get("cpu", samples[-1][3] if samples else 0.0) - (before[-1] if before else 0.0)
    return Measurement(wall_s=output["end"] - output["start"] if "end" in output else wall, peak_rss=peak,
                       bytes_written=written, cpu_s=max(0.0, cpu), samples=samples, start=output["start"],
                       result=output.get("result"), error=output.get("error"))


if __name__ == "__main__":
    _child(sys.argv[1], sys.argv[2])
