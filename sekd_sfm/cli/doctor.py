"""``sekd doctor``: what this installation and machine can do."""
from __future__ import annotations

import importlib.metadata
import os

import click
import torch

from sekd_sfm.failures import DEBUG_VARIABLE, debug_enabled
from sekd_sfm.files.images import DEFAULT_MAX_PIXELS
from sekd_sfm.model.fused import ENV_SWITCH, fused_forward_available
from sekd_sfm.model.weights import EMBEDDED_MODEL, file_sha256
from sekd_sfm.runtime import (
    cpu_description,
    cpu_has_fast_bf16,
    cpu_reports_bf16,
    package_versions,
)


@click.command()
def doctor() -> None:
    """Print library versions, CPU features, threads, and whether the embedded model and a GPU are found."""
    for name, version in package_versions().items():
        click.echo(f"{name:<18}{version}")
    cpu = cpu_description()
    click.echo(f"{'cpu':<18}{cpu['model']}")
    click.echo(f"{'cpu features':<18}" + " ".join(f"{f}:{'yes' if yes else 'no'}" for f, yes in cpu["features"].items()))
    click.echo(f"{'torch cpu kernels':<18}{cpu['torch_kernels']}")
    click.echo(f"{'threads':<18}{torch.get_num_threads()} intra-op (set with --num-threads)")
    click.echo(f"{'precision auto':<18}{_auto_precision_reason()}")
    fused = (f"on: oneDNN fused residual blocks on the CPU; {ENV_SWITCH}=0 turns them off" if fused_forward_available()
             else "off: the eager PyTorch forward")
    click.echo(f"{'fused forward':<18}{ENV_SWITCH}={os.environ.get(ENV_SWITCH, '')!s} ({fused})")
    model = f"{EMBEDDED_MODEL} (sha256 {file_sha256(EMBEDDED_MODEL)})" if EMBEDDED_MODEL.is_file() else "not found: pass --weights"
    click.echo(f"{'embedded model':<18}{model}")
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none (CPU only)"
    click.echo(f"{'gpu':<18}{gpu}")
    ram = _physical_memory()
    click.echo(f"{'memory':<18}{ram / 2**30:.1f} GB" if ram else f"{'memory':<18}unknown")
    click.echo(f"{'pixel cap':<18}{DEFAULT_MAX_PIXELS / 1e6:g} MP per image (extract/reconstruct --max-pixels)")
    click.echo(f"{'pixel budget':<18}{_tile_budget()}")
    for name, line in _extras().items():
        click.echo(f"{name:<18}{line}")
    state = "on: failures show the traceback" if debug_enabled() else "off: failures print one Error: line"
    click.echo(f"{'debug':<18}{DEBUG_VARIABLE}={os.environ.get(DEBUG_VARIABLE, '')!s} ({state})")


#: Optional extras: (what they enable, the packages whose versions show they are installed).
EXTRAS = {
    "ray": ("--executor ray", ("ray",)),
    "int8": ("--precision int8", ("openvino", "nncf")),
    "viz": ("export --format html", ("plotly",)),
}


def _extras() -> dict[str, str]:
    """``extra ray -> "2.60.0 (--executor ray); ..."``: each optional extra, installed or the command that installs it."""
    lines, installed = {}, set()
    for extra, (enables, packages) in EXTRAS.items():
        try:  # metadata only: importing Ray or OpenVINO takes seconds
            versions = [f"{name} {importlib.metadata.version(name)}" for name in packages]
        except importlib.metadata.PackageNotFoundError:
            lines[f"extra {extra}"] = f'not installed ({enables}: pip install "sekd-sfm[{extra}]")'
            continue
        lines[f"extra {extra}"] = f"{', '.join(versions)} ({enables})"
        installed.add(extra)
    if "ray" in installed:
        lines["ray cluster here"] = _ray_cluster_here()
    return lines


def _ray_cluster_here() -> str:
    """The Ray cluster ``--ray-address auto`` would join from here, or what it does instead."""
    from sekd_sfm.execution.ray_connect import (
        _running_cluster_address,
        address_variable,
    )

    if address_variable():
        return f"$RAY_ADDRESS={address_variable()} (what --ray-address auto uses)"
    address = _running_cluster_address([])
    if address and address != "auto":
        return f"{address} (what --ray-address auto joins)"
    return "none running: --executor ray would start a local one for each run (`ray start --head` keeps one)"


def _physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def _auto_precision_reason() -> str:
    """What ``--precision auto`` picks here, and why."""
    if cpu_has_fast_bf16():
        return "bf16 (native bf16 found)"
    if cpu_reports_bf16():
        return (f"fp32 (the CPU has native bf16, but oneDNN may not use it: ONEDNN_MAX_CPU_ISA="
                f"{os.environ.get('ONEDNN_MAX_CPU_ISA', 'unset')})")
    return "fp32 (no native bf16)"


def _tile_budget() -> str:
    """SEKD's pixels per forward pass (``model.tiling``): larger images run in tiles, so memory stays bounded."""
    from sekd_sfm.model.tiling import (
        BYTES_PER_PIXEL,
        MEMORY_SHARE,
        memory_limit,
        pixel_budget,
    )

    limit = memory_limit()
    budget = pixel_budget()
    return (f"{budget / 1e6:.1f} MP per SEKD forward pass, about {budget * BYTES_PER_PIXEL / 2**30:.1f} GB "
            f"(1/{round(1 / MEMORY_SHARE)} of {limit / 2**30:.1f} GB); larger images run in tiles "
            "(SEKD_PIXEL_BUDGET overrides)")
