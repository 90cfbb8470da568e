"""How long a larger collection would take: each stage's measured time carried to N photos by its growth exponent.

``bench scale`` measures a few sizes; planning asks about 10,000 or 100,000 photos. A stage's time grows as
N^b, with b fitted on log-log over the measured sizes (``growth_exponent``); the projection carries the largest
measured size's time of each stage to N with its own b, and sums the stages, so the stage that grows fastest
decides the large sizes (a total fitted as one power law would not). Only sizes measured on one machine and
commit enter a fit: across machines the speeds, not the growth, would make the slope. A projection is a plan,
not a measurement: two sizes make a straight line, and whatever breaks between them and N (memory, a solver
that changes its method) is not in it.
"""
from __future__ import annotations

import math

import numpy as np

from ...runtime import cpu_text

#: The collection sizes every report projects to (photos).
PROJECTED_SIZES = (10_000, 100_000)


def growth_exponent(sizes: list[int], values: list[float]) -> float | None:
    """Slope of log(value) against log(size) by least squares; None with fewer than 2 positive points."""
    points = [(math.log(s), math.log(v)) for s, v in zip(sizes, values) if v and v > 0]
    if len(points) < 2 or len({p[0] for p in points}) < 2:
        return None
    x, y = np.array(points).T
    return float(np.polyfit(x, y, 1)[0])


def _run_key(result: dict) -> tuple:
    """The machine and commit a size ran on (``result["run"]``, ``runtime.run_record``); () when not recorded.
    The machine as the report's "Measured:" line names it (``runtime.cpu_text``), so both group sizes alike."""
    run = result.get("run") or {}
    return (cpu_text(run.get("cpu", "?")), run.get("commit")) if run else ()


def same_run_sizes(results: list[dict], pipeline: str = "ours") -> list[dict]:
    """The results of ``pipeline`` measured on the machine and commit of its largest size, smallest first.

    Sizes that stopped before a stage (``skipped``) or failed are left out: their totals are not whole runs.
    """
    rows = [r for r in results if pipeline in r and not r[pipeline].get("skipped") and not r[pipeline].get("failure")]
    if not rows:
        return []
    largest = max(rows, key=lambda r: r["size"])
    return sorted((r for r in rows if _run_key(r) == _run_key(largest)), key=lambda r: r["size"])


def project(results: list[dict], stages: tuple[str, ...], sizes: tuple[int, ...] = PROJECTED_SIZES,
            pipeline: str = "ours", key: str = "time_s") -> dict | None:
    """Each stage's time (``key``: "time_s" wall or "cpu_s", seconds) projected to ``sizes`` photos.

    ``stages`` orders the stages; those the largest size ran beyond them follow in its order.

    Returns ``{"from_sizes": [...], "exponents": {stage: b}, "projected": {N: {stage: s, ..., "total": s}}}``, or
    None with fewer than two sizes from one machine and commit. A stage measured at only one size, or whose fit
    fails, is carried linearly (b = 1) and named in ``"linear"``.
    """
    rows = same_run_sizes(results, pipeline)
    if len(rows) < 2:
        return None
    measured = [r["size"] for r in rows]
    base = rows[-1]
    exponents, linear, projected = {}, [], {n: {} for n in sizes}
    measured_stages = base[pipeline]["stages"]
    # Every stage the largest size ran, ``stages``' order first: a step outside it (a model check, a remap in
    # capture order) is time the collection costs as well.
    for stage in [s for s in stages if s in measured_stages] + [s for s in measured_stages if s not in stages]:
        b = growth_exponent(measured, [r[pipeline]["stages"].get(stage, {}).get(key, 0) for r in rows])
        if b is None:
            b = 1.0
            linear.append(stage)
        exponents[stage] = round(b, 3)
        for n in sizes:
            projected[n][stage] = measured_stages[stage].get(key, 0) * (n / base["size"]) ** b
    for n in sizes:
        projected[n]["total"] = sum(projected[n].values())
    return {"from_sizes": measured, "key": key, "exponents": exponents, "linear": linear, "projected": projected}


def projection_markdown(projection: dict | None) -> list[str]:
    """The report's lines for ``project``'s result: where it comes from, then one row per projected size."""
    if not projection:
        return []
    shown = list(projection["exponents"])
    what = "wall time" if projection["key"] == "time_s" else "CPU time"
    lines = [(f"Projected {what} (s) of our pipeline on larger collections: each stage's time at N = "
              f"{projection['from_sizes'][-1]} carried by its growth exponent fitted over N = "
              f"{', '.join(map(str, projection['from_sizes']))} (one machine and commit), the stages summed. "
              "A plan, not a measurement: nothing that breaks beyond the measured sizes is in it."
              + (f" Carried linearly (one size only): {', '.join(projection['linear'])}." if projection["linear"]
                 else "")), "",
             "| N | " + " | ".join(shown) + " | total | hours |", "|---|" + "---|" * (len(shown) + 2),
             "| exponent | " + " | ".join(f"{projection['exponents'][s]:.2f}" for s in shown) + " | | |"]
    for n, row in projection["projected"].items():
        lines.append(f"| {n:,} | " + " | ".join(f"{row[s]:.0f}" for s in shown)
                     + f" | {row['total']:.0f} | {row['total'] / 3600:.1f} |")
    return lines
