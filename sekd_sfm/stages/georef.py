"""Georeferencing (``reconstruct --gps``): a model in metres on the Earth from the photos' EXIF GPS.

Frame: local ENU (x east, y north, z up, metres) about an origin, the mean latitude,
longitude and altitude of the photos with GPS; positions go WGS84 (lat, lon, alt) -> ECEF
-> ENU. After mapping, the model's camera centres are aligned to the GPS positions by a
similarity (scale, rotation, translation): LO-RANSAC (``pycolmap.estimate_sim3d_robust``,
threshold ``GpsConfig.max_error_m``), then a least-squares fit on the inliers, where a
position is an inlier when its residual is at most ``max(max_error_m, 5 sigma)``, sigma the
residuals' robust spread (so metre-level GPS noise does not make good photos outliers while
a position tens of metres off still is; see INLIER_SIGMAS). The whole model (cameras and points) is
transformed, so ``model/`` and every export of it are in the ENU frame.

Altitude rule: the altitude is used only when every photo with GPS has one. Otherwise all
are set to 0 (the camera centres are assumed to lie in a horizontal plane at the origin),
``vertical_constrained`` is false and the residuals are horizontal distances.

Not georeferenced (a warning, the model kept as mapped, the record's ``georeference`` says
why, no georef.json): fewer than 3 registered photos with GPS, positions all within
``min_spread_m`` of each other, positions on a line (their second principal spread below
``min_spread_m`` or 2 % of the first: the rotation about the line is undetermined), model
camera centres on a line, or no similarity found.
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..files import features as ff
from ..files.atomic import write_json
from ..files.gps import GPSPosition, read_gps
from ..files.images import list_images
from ..runtime import package_versions
from .colmap import require_pycolmap
from .pairs import GpsNeighbors

logger = logging.getLogger("sekd")
GPS_MODES = ("auto", "off", "pairs", "align")
#: WGS84 ellipsoid: semi-major axis (m) and flattening.
WGS84_A = 6378137.0
WGS84_F = 1 / 298.257223563
WGS84_E2 = WGS84_F * (2 - WGS84_F)
#: Photos with GPS needed for a similarity (3 non-collinear points fix its 7 degrees of freedom).
MIN_GPS_PHOTOS = 3
#: Positions whose second principal spread is below this fraction of the first are "on a line".
COLLINEAR_RATIO = 0.02
GEOREF_FILE = "georef.json"
#: Inlier threshold in robust standard deviations of the residuals. The residuals of a similarity fitted to
#: few photos underestimate the GPS noise (7 parameters absorb part of it), so 3 sigma drops good photos:
#: fountain-P11 (11 photos, 5 m spread), GPS noise 2 m per axis, 100 draws, median camera-centre error after
#: alignment 1.97 m at 3, 1.59 m at 4, 1.43 m at 5, 1.38 m for least squares on all photos; with one
#: position 40 m off, 1.52 m at 5 (the outlier still rejected).
INLIER_SIGMAS = 5.0


@dataclass
class GpsConfig:
    """How EXIF GPS is used: ``mode`` in GPS_MODES (auto = pairs + align when at least 3 photos carry GPS).

    ``max_error_m``: RANSAC inlier threshold of the alignment (metres; the final inlier threshold is
    at least this, see the module docstring). ``neighbors`` / ``radius_m``: each photo is paired
    with its ``neighbors`` nearest photos by GPS within ``radius_m`` metres. ``min_spread_m``:
    positions spread less than this (overall, or across their main line) are degenerate.
    """

    mode: str = "auto"
    max_error_m: float = 3.0
    neighbors: int = 10
    radius_m: float = 100.0
    min_spread_m: float = 1.0


@dataclass
class GpsPlan:
    """What a run does with GPS, decided from the photos before pairing (``plan_gps``)."""

    mode: str
    pairs: bool = False
    align: bool = False
    reason: str = ""
    photos: int = 0
    origin: GPSPosition | None = None
    vertical_constrained: bool = True
    #: ENU positions (metres, x east, y north, z up) of the photos with GPS, by image name.
    positions: dict[str, np.ndarray] = field(default_factory=dict)

    def neighbors(self, config: GpsConfig) -> GpsNeighbors | None:
        """The GPS neighbour pairs to add to the pairs stage, None when GPS pairs are off."""
        if not self.pairs:
            return None
        return GpsNeighbors({name: tuple(map(float, p)) for name, p in self.positions.items()},
                            config.neighbors, config.radius_m)

    def summary(self) -> dict:
        return {"mode": self.mode, "pairs": self.pairs, "align": self.align, "reason": self.reason,
                "photos": self.photos, "photos_with_gps": len(self.positions),
                "origin": asdict(self.origin) if self.origin else None,
                "vertical_constrained": self.vertical_constrained}


# ----------------------------------------------------------------------------- WGS84 <-> ECEF <-> ENU

def ecef_from_geodetic(lat_lon_alt: np.ndarray) -> np.ndarray:
    """WGS84 (N, 3) latitude, longitude (degrees), ellipsoidal height (m) -> ECEF (N, 3) metres."""
    lla = np.atleast_2d(np.asarray(lat_lon_alt, np.float64))
    lat, lon, alt = np.radians(lla[:, 0]), np.radians(lla[:, 1]), lla[:, 2]
    n = WGS84_A / np.sqrt(1 - WGS84_E2 * np.sin(lat) ** 2)  # prime vertical radius of curvature
    return np.stack([(n + alt) * np.cos(lat) * np.cos(lon), (n + alt) * np.cos(lat) * np.sin(lon),
                     (n * (1 - WGS84_E2) + alt) * np.sin(lat)], axis=1)


def geodetic_from_ecef(xyz: np.ndarray) -> np.ndarray:
    """ECEF (N, 3) metres -> WGS84 (N, 3) latitude, longitude (degrees), height (m); fixed-point iteration
    on the latitude (converges to < 1e-12 rad in a few steps away from the Earth's centre)."""
    xyz = np.atleast_2d(np.asarray(xyz, np.float64))
    p = np.hypot(xyz[:, 0], xyz[:, 1])
    lon = np.arctan2(xyz[:, 1], xyz[:, 0])
    lat = np.arctan2(xyz[:, 2], p * (1 - WGS84_E2))
    for _ in range(10):
        n = WGS84_A / np.sqrt(1 - WGS84_E2 * np.sin(lat) ** 2)
        alt = p / np.cos(lat) - n
        lat = np.arctan2(xyz[:, 2], p * (1 - WGS84_E2 * n / (n + alt)))
    n = WGS84_A / np.sqrt(1 - WGS84_E2 * np.sin(lat) ** 2)
    alt = p / np.cos(lat) - n
    return np.stack([np.degrees(lat), np.degrees(lon), alt], axis=1)


def enu_rotation(latitude: float, longitude: float) -> np.ndarray:
    """3x3 rotation whose rows are the east, north and up unit vectors in ECEF at (latitude, longitude) degrees."""
    lat, lon = np.radians(latitude), np.radians(longitude)
    return np.array([[-np.sin(lon), np.cos(lon), 0.0],
                     [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
                     [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)]])


def enu_from_geodetic(lat_lon_alt: np.ndarray, origin: GPSPosition) -> np.ndarray:
    """WGS84 (N, 3) lat, lon (deg), alt (m) -> ENU (N, 3) metres about ``origin`` (x east, y north, z up)."""
    ref = ecef_from_geodetic([[origin.latitude, origin.longitude, origin.altitude or 0.0]])[0]
    return (ecef_from_geodetic(lat_lon_alt) - ref) @ enu_rotation(origin.latitude, origin.longitude).T


def geodetic_from_enu(enu: np.ndarray, origin: GPSPosition) -> np.ndarray:
    """ENU (N, 3) metres about ``origin`` -> WGS84 (N, 3) lat, lon (deg), alt (m); inverse of enu_from_geodetic."""
    ref = ecef_from_geodetic([[origin.latitude, origin.longitude, origin.altitude or 0.0]])[0]
    return geodetic_from_ecef(np.atleast_2d(enu) @ enu_rotation(origin.latitude, origin.longitude) + ref)


def frame_description(origin: GPSPosition) -> str:
    return (f"ENU, metres, origin lat {origin.latitude:.8f} lon {origin.longitude:.8f} alt "
            f"{origin.altitude or 0.0:.3f} m (WGS84): x east, y north, z up")


# ----------------------------------------------------------------------------- planning

def degenerate_reason(positions: np.ndarray, min_spread_m: float, what: str = "GPS positions") -> str | None:
    """Why ``positions`` (N, 3) cannot fix a similarity's rotation, None when they can.

    Spreads are RMS distances from the centroid along the principal axes (metres for GPS).
    """
    if len(positions) < MIN_GPS_PHOTOS:
        return f"{what} of {len(positions)} photo(s): at least {MIN_GPS_PHOTOS} are needed"
    spread = np.linalg.svd(positions - positions.mean(0), compute_uv=False) / np.sqrt(len(positions))
    if spread[0] < min_spread_m:
        return f"{what} all within {min_spread_m:g} m of each other (spread {spread[0]:.2f} m)"
    if spread[1] < max(min_spread_m, COLLINEAR_RATIO * spread[0]):
        return (f"{what} on a line (spread {spread[0]:.2f} m along it, {spread[1]:.2f} m across): "
                "the rotation about the line is undetermined")
    return None


def read_positions(image_dir: Path, names: list[str]) -> dict[str, GPSPosition]:
    """EXIF GPS of the photos ``names`` below ``image_dir``, for those that have it."""
    found = {name: read_gps(image_dir / name) for name in names}
    return {name: position for name, position in found.items() if position is not None}


def photo_names(image_dir: str | Path, features: str | Path | None = None) -> list[str]:
    """The photos of a run: the feature file's images when given, else those below ``image_dir``
    ([] when neither can be listed: the stage that needs them says why)."""
    try:
        return ff.list_keys(Path(features)) if features is not None else list_images(image_dir)
    except (SekdError, OSError):
        return []


def plan_gps(image_dir: str | Path, names: list[str], config: GpsConfig) -> GpsPlan:
    """Read the photos' GPS and decide what ``config.mode`` does with it (logged: info or one warning)."""
    if config.mode not in GPS_MODES:
        raise SekdError(f"unknown --gps mode {config.mode!r}; choose from {', '.join(GPS_MODES)}")
    plan = GpsPlan(config.mode, photos=len(names))
    if config.mode == "off":
        plan.reason = "--gps off"
        return plan
    found = read_positions(Path(image_dir), names)
    if len(found) < MIN_GPS_PHOTOS:
        plan.reason = f"EXIF GPS on {len(found)} of {len(names)} photos (at least {MIN_GPS_PHOTOS} needed)"
        if found or config.mode != "auto":  # auto on photos without GPS (the common case) stays quiet
            logger.warning("warning: %s: the model is not georeferenced", plan.reason)
        return plan
    _set_positions(plan, found)
    plan.pairs = config.mode in ("auto", "pairs")
    plan.align = config.mode in ("auto", "align")
    plan.reason = "" if plan.align else "--gps pairs: GPS pairs only, no alignment"
    if plan.align and (reason := degenerate_reason(np.stack(list(plan.positions.values())), config.min_spread_m)):
        plan.align, plan.reason = False, reason
        logger.warning("warning: %s: the model is not georeferenced", reason)
    logger.info("EXIF GPS on %d of %d photos%s: %s", len(found), len(names),
                "" if plan.vertical_constrained else " (altitude missing on some: vertical unconstrained)",
                " + ".join(s for s, on in (("GPS pairs", plan.pairs), ("alignment", plan.align)) if on) or "unused")
    return plan


def _set_positions(plan: GpsPlan, found: dict[str, GPSPosition]) -> None:
    """The origin (mean lat, lon, alt) and ENU positions; altitudes all 0 unless every photo has one."""
    plan.vertical_constrained = all(p.altitude is not None for p in found.values())
    lla = np.array([[p.latitude, p.longitude, p.altitude if plan.vertical_constrained else 0.0]
                    for p in found.values()])
    mean = lla.mean(0)
    plan.origin = GPSPosition(float(mean[0]), float(mean[1]), float(mean[2]))
    plan.positions = dict(zip(found, enu_from_geodetic(lla, plan.origin)))


# ----------------------------------------------------------------------------- alignment

def camera_centres(reconstruction) -> dict[str, np.ndarray]:
    """Camera centres (3,) in model coordinates of the registered images, by name."""
    return {reconstruction.image(i).name: np.asarray(reconstruction.image(i).projection_center())
            for i in reconstruction.reg_image_ids()}


def _residuals(sim, src: np.ndarray, tgt: np.ndarray, vertical: bool) -> np.ndarray:
    diff = np.asarray(sim * src).reshape(-1, 3) - tgt
    return np.linalg.norm(diff if vertical else diff[:, :2], axis=1)


def robust_similarity(src: np.ndarray, tgt: np.ndarray, max_error_m: float, vertical: bool = True,
                      seed: int = 0):
    """tgt_from_src similarity of (N, 3) point sets: LO-RANSAC, then least squares on the inliers.

    Returns (pycolmap Sim3d, residuals (N,) metres, inlier mask (N,), inlier threshold m), or None
    when no similarity with at least 3 inliers is found. Inliers: residual <= max(max_error_m,
    INLIER_SIGMAS sigma), sigma = median residual / the median of a chi distribution (3 dof, or 2
    when not ``vertical``: residuals horizontal), a spread robust to outliers.
    """
    pycolmap = require_pycolmap()
    options = pycolmap.RANSACOptions()
    options.max_error, options.random_seed = max_error_m, seed
    found = pycolmap.estimate_sim3d_robust(src, tgt, options)  # {tgt_from_src, num_inliers, inlier_mask} or None
    if not found or found.get("tgt_from_src") is None:
        return None
    sim = found["tgt_from_src"]
    chi_median = 1.5382 if vertical else 1.1774  # medians of chi with 3 / 2 degrees of freedom
    threshold = max_error_m
    for _ in range(5):  # refit on the inliers (they settle in a few rounds)
        residuals = _residuals(sim, src, tgt, vertical)
        threshold = max(max_error_m, INLIER_SIGMAS * float(np.median(residuals)) / chi_median)
        inliers = residuals <= threshold
        if inliers.sum() < MIN_GPS_PHOTOS:
            return None
        refit = pycolmap.estimate_sim3d(src[inliers], tgt[inliers])
        if refit is None:
            return None
        sim = refit
    residuals = _residuals(sim, src, tgt, vertical)
    return sim, residuals, residuals <= threshold, threshold


def georeference(models: list, plan: GpsPlan, config: GpsConfig, seed: int = 0) -> dict:
    """Align ``models[0]`` (the main model, transformed in place) to the GPS positions of ``plan``.

    Returns the run's record's ``georeference`` entry (and georef.json when ``georeferenced``):
    origin, frame, similarity, per-image residuals (metres), median / max, inliers, or why not.
    """
    record = {"georeferenced": False, **plan.summary()}
    if not plan.align or not models:
        return record
    centres = camera_centres(models[0])
    names = sorted(set(centres) & set(plan.positions))
    src = np.array([centres[n] for n in names]).reshape(-1, 3)
    tgt = np.array([plan.positions[n] for n in names]).reshape(-1, 3)
    reason = degenerate_reason(tgt, config.min_spread_m, "GPS positions of the registered photos")
    if reason is None and len(src):
        # The model's centres have no metric scale: only their shape is judged.
        spread = np.linalg.svd(src - src.mean(0), compute_uv=False)
        reason = ("the model's camera centres lie on a line: the rotation about it is undetermined"
                  if spread[1] < COLLINEAR_RATIO * spread[0] else None)
    fit = None if reason else robust_similarity(src, tgt, config.max_error_m, plan.vertical_constrained, seed)
    if reason or fit is None:
        record["reason"] = reason or f"no similarity with {MIN_GPS_PHOTOS}+ GPS inliers within {config.max_error_m} m"
        logger.warning("warning: %s: the model is not georeferenced", record["reason"])
        return record
    sim, residuals, inliers, threshold = fit
    models[0].transform(sim)
    record.update(_alignment_record(sim, names, residuals, inliers, threshold, plan, config))
    logger.info("georeferenced: %d/%d GPS inliers, median residual %.2f m, scale %.4g m per model unit (%s)",
                inliers.sum(), len(names), record["median_residual_m"], record["scale"], GEOREF_FILE)
    return record


def _alignment_record(sim, names: list[str], residuals: np.ndarray, inliers: np.ndarray, threshold: float,
                      plan: GpsPlan, config: GpsConfig) -> dict:
    return {
        "georeferenced": True, "reason": "",
        "frame": frame_description(plan.origin),
        "residuals": "horizontal" if not plan.vertical_constrained else "3D",
        "scale": float(sim.scale), "rotation_xyzw": [float(v) for v in sim.rotation.quat],
        "translation": [float(v) for v in np.asarray(sim.translation).ravel()],
        "aligned_images": len(names), "inliers": int(inliers.sum()), "inlier_threshold_m": float(threshold),
        "median_residual_m": float(np.median(residuals[inliers])), "max_residual_m": float(residuals[inliers].max()),
        "median_residual_all_m": float(np.median(residuals)), "max_residual_all_m": float(residuals.max()),
        "per_image": {name: {"residual_m": round(float(r), 4), "inlier": bool(i)}
                      for name, r, i in zip(names, residuals, inliers)},
        "config": asdict(config),
    }


def write_georef(out: str | Path, record: dict) -> Path | None:
    """``out``/georef.json for a georeferenced model (with versions), else remove a stale one; its path or None."""
    path = Path(out) / GEOREF_FILE
    if not record.get("georeferenced"):
        path.unlink(missing_ok=True)
        return None
    return write_json({**record, "versions": package_versions()}, path)
