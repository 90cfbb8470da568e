"""One clear line for any failure that is not a SekdError: OS errors, memory, HDF5 and torch.

The CLI's top-level handler (``sekd_sfm/cli/main.py``) prints :func:`explain`'s line as ``Error: ...``
and exits with code 1. Every stage saves finished work before it can fail (parts files,
per-epoch checkpoints), so the messages can promise that running the same command again
resumes. ``SEKD_DEBUG=1`` in the environment shows the traceback instead.
"""
from __future__ import annotations

import errno
import json
import os
import pickle
import re
import shutil
from collections.abc import Iterable
from pathlib import Path

#: Environment variable that makes the CLI re-raise instead of printing one line.
DEBUG_VARIABLE = "SEKD_DEBUG"
_RESUME = "run the same command again to resume where it stopped"


def debug_enabled() -> bool:
    """True when ``SEKD_DEBUG`` is set to something other than empty or 0."""
    return os.environ.get(DEBUG_VARIABLE, "") not in ("", "0")


def explain(exc: BaseException, inputs: Iterable[str] = ()) -> str:
    """A one-line, user-facing description of ``exc`` saying what to do.

    ``inputs``: the command's arguments, used to name the HDF5 file h5py did not name.
    """
    inputs = [str(a) for a in inputs]
    if isinstance(exc, OSError) and (exc.errno is not None or exc.filename is not None):
        return _os_error(exc, _output_of(inputs))
    if isinstance(exc, MemoryError) or is_out_of_memory(exc):
        return ("out of memory; lower --resize-max or --max-pixels, use fewer --max-keypoints or --num-threads, "
                "or close other programs, then " + _RESUME)
    if _from_module(exc, "h5py") or isinstance(exc, OSError) and "file signature" in str(exc):
        return f"{_hdf5_files(inputs)}: damaged or not the expected kind of HDF5 file ({first_line(exc)})"
    if isinstance(exc, pickle.UnpicklingError) or _is_bad_checkpoint(exc):
        return f"cannot load a model checkpoint: not a valid PyTorch weights file ({first_line(exc)})"
    return (f"unexpected {type(exc).__name__}: {first_line(exc)} "
            f"(set {DEBUG_VARIABLE}=1 to see the traceback, and please report it)")


def _output_of(args: list[str]) -> str | None:
    """The value of ``-o``/``--output``/``--out`` among the command's arguments, if given."""
    for i, arg in enumerate(args):
        for flag in ("-o", "--output", "--out"):
            if arg == flag and i + 1 < len(args):
                return args[i + 1]
            if arg.startswith(flag + "=") and flag != "-o":
                return arg.split("=", 1)[1]
    return None


def _os_error(exc: OSError, output: str | None = None) -> str:
    # h5py does not set ``filename`` but names the file in its message ("filename = '...'").
    named = re.search(r"\bname = '([^']*)'", str(exc))
    path = exc.filename if exc.filename is not None else named.group(1) if named else output or "(unnamed file)"
    code = exc.errno
    if code in (errno.ENOSPC, errno.EDQUOT):
        return (f"disk full while writing {path}{_free_space(path)}; everything finished before is kept"
                f"{_saved(output)}: free some space (or choose an output on another disk) and {_RESUME}")
    if code in (errno.EACCES, errno.EPERM):
        return f"{path}: permission denied; check the permissions of this path and its folder, or choose another"
    if code == errno.EROFS:
        return f"{path}: the file system is read-only; choose an output on a writable disk"
    if code == errno.ENOTDIR:
        return f"{path}: {_file_in_path(path)} is a file, not a folder; choose another path"
    if code == errno.EEXIST:  # mkdir(exist_ok=True) on a file
        return f"{path}: is a file where a folder is needed; choose another path"
    if code == errno.EISDIR:
        return f"{path}: is a folder where a file is expected; give a file name"
    if code == errno.ENOENT:
        return f"{path}: no such file or folder"
    if code == errno.EIO:
        return f"{path}: input/output error (a failing disk or a lost network share?); check the disk, then {_RESUME}"
    if code in (errno.EMFILE, errno.ENFILE):
        return f"{path}: too many open files; raise the limit (ulimit -n) and {_RESUME}"
    if code == errno.ENOMEM:
        return "out of memory; lower --resize-max or --max-pixels, or close other programs, then " + _RESUME
    reason = exc.strerror or first_line(exc)
    return f"{path}: {reason}" + (f" (and {exc.filename2})" if exc.filename2 else "")


def _free_space(path: str) -> str:
    """`` (N MB free there)`` for the nearest existing folder of ``path``; empty when unknown."""
    folder = Path(path).parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        return f" ({shutil.disk_usage(folder).free / 1e6:.0f} MB free there)"
    except OSError:
        return ""


def _saved(output: str | None) -> str:
    """`` (N images in OUTPUT ...)``: what a feature file or a run folder holds (best effort; empty if unknown)."""
    if not output:
        return ""
    path = Path(output)
    try:
        if (path / "state.json").is_file():
            done = json.loads((path / "state.json").read_text()).get("done", [])
            return f" ({len(done)} finished training tasks in {path})"
        if path.is_file() and path.suffix.lower() in (".h5", ".hdf5"):
            from .files.features import list_keys

            parts = path.with_name(path.name + ".parts")
            more = f", more in {parts}" if parts.is_dir() and any(parts.iterdir()) else ""
            return f" ({len(list_keys(path))} images in {path}{more})"
    except Exception:  # noqa: BLE001 - a summary must never hide the disk-full message itself
        return ""
    return ""


def _file_in_path(path: str) -> str:
    """The first component of ``path`` that exists as a non-folder (the cause of ENOTDIR)."""
    for parent in reversed(Path(path).parents):
        if parent.exists() and not parent.is_dir():
            return str(parent)
    return "a part of this path"


def _hdf5_files(inputs: Iterable[str]) -> str:
    files = [a for a in inputs if str(a).lower().endswith((".h5", ".hdf5")) and Path(a).is_file()]
    return ", ".join(files) if files else "an HDF5 input"


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type name when empty), at most 300 characters."""
    text = str(exc).strip()
    if isinstance(exc, KeyError) and text.startswith(("'", '"')):
        text = text[1:-1]
    return (text.splitlines() or [type(exc).__name__])[0][:300]


def _from_module(exc: BaseException, module: str) -> bool:
    """True when ``exc`` was raised inside ``module`` (its deepest frame)."""
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    name = tb.tb_frame.f_globals.get("__name__", "") if tb is not None else ""
    return name == module or name.startswith(module + ".")


def is_out_of_memory(exc: BaseException) -> bool:
    text = str(exc)
    return type(exc).__name__ == "OutOfMemoryError" or (
        isinstance(exc, RuntimeError) and ("can't allocate memory" in text or "out of memory" in text))


def _is_bad_checkpoint(exc: BaseException) -> bool:
    text = str(exc)
    return isinstance(exc, RuntimeError) and any(
        s in text for s in ("PytorchStreamReader", "Invalid magic number", "Error(s) in loading state_dict",
                            "Weights only load failed", "invalid load key"))
