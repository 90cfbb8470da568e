"""EXIF GPS of photos: read (``read_gps``, no pixel decoding) and write (``write_gps``, for tests and benchmarks).

EXIF stores a position in the GPS IFD (tag 0x8825) as degrees, minutes and seconds (three
rationals) with a hemisphere letter (``N``/``S``, ``E``/``W``), and the altitude as one rational
in metres with a reference byte (0 above, 1 below sea level). ``GPSPosition`` holds the decoded
WGS84 latitude and longitude in degrees (south and west negative) and the altitude in metres
(None when the photo has none).

``write_gps`` puts the tags into a copy of a JPEG without re-encoding it: the file's Exif
segment (APP1) is replaced, or inserted after the start marker, and every other byte is kept,
so the pixels stay identical. Other formats are re-saved by PIL (lossless for PNG and TIFF).
"""
from __future__ import annotations

import logging
import math
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational

from .atomic import write_atomic

logger = logging.getLogger("sekd")
GPS_IFD = 0x8825
#: Denominator of the seconds written by ``write_gps``: 1e-6 s = 3e-10 deg, ~0.03 mm on the ground.
SECONDS_DENOMINATOR = 10**6
#: Denominator of the altitude written by ``write_gps`` (millimetres).
ALTITUDE_DENOMINATOR = 1000


@dataclass(frozen=True)
class GPSPosition:
    """A photo's WGS84 position: latitude, longitude (degrees, north / east positive), altitude (metres or None)."""

    latitude: float
    longitude: float
    altitude: float | None = None


def _degrees(value, ref) -> float:
    """Degrees of an EXIF (deg, min, sec) triple (or a single number) and its N/S/E/W reference."""
    parts = [float(v) for v in (value if isinstance(value, (tuple, list)) else (value,))]
    if not parts or len(parts) > 3 or not all(math.isfinite(p) for p in parts):
        raise ValueError(f"bad GPS angle {value!r}")
    degrees = sum(p / 60**i for i, p in enumerate(parts))
    ref = ref.decode("ascii", "replace") if isinstance(ref, bytes) else str(ref or "")
    return -degrees if ref.strip().upper()[:1] in ("S", "W") else degrees


def _altitude(gps: dict) -> float | None:
    value = gps.get(ExifTags.GPS.GPSAltitude)
    if value is None:
        return None
    altitude = float(value)
    if not math.isfinite(altitude):
        return None
    ref = gps.get(ExifTags.GPS.GPSAltitudeRef, 0)
    below = (ref[:1] == b"\x01") if isinstance(ref, bytes) else int(ref or 0) == 1
    return -altitude if below else altitude


def read_gps(path: str | Path) -> GPSPosition | None:
    """The EXIF GPS position of the photo ``path``, None when it has none or it is unreadable.

    Only the file's header is parsed (PIL opens lazily; the pixels are not decoded). A
    position of exactly (0, 0) is taken as a camera's placeholder and ignored.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # PIL warns of corrupt EXIF; it is reported as no GPS below
            with Image.open(path) as image:
                gps = image.getexif().get_ifd(GPS_IFD)
        if ExifTags.GPS.GPSLatitude not in gps or ExifTags.GPS.GPSLongitude not in gps:
            return None
        latitude = _degrees(gps[ExifTags.GPS.GPSLatitude], gps.get(ExifTags.GPS.GPSLatitudeRef))
        longitude = _degrees(gps[ExifTags.GPS.GPSLongitude], gps.get(ExifTags.GPS.GPSLongitudeRef))
        altitude = _altitude(gps)
    except (OSError, ValueError, TypeError, KeyError, IndexError, AttributeError, ZeroDivisionError, SyntaxError,
            struct.error) as exc:  # a malformed EXIF block is "no GPS", never a failed run
        logger.debug("%s: no usable EXIF GPS (%s)", path, exc)
        return None
    if abs(latitude) > 90 or abs(longitude) > 180 or (latitude == 0 and longitude == 0):
        return None
    return GPSPosition(latitude, longitude, altitude)


def _dms(degrees: float) -> tuple[IFDRational, IFDRational, IFDRational]:
    """|degrees| as EXIF (deg, min, sec) rationals, seconds to 1e-6."""
    total = round(abs(degrees) * 3600 * SECONDS_DENOMINATOR)  # integer micro-seconds of arc
    seconds_per_degree = 3600 * SECONDS_DENOMINATOR
    deg, rest = divmod(total, seconds_per_degree)
    minutes, micro = divmod(rest, 60 * SECONDS_DENOMINATOR)
    return IFDRational(deg, 1), IFDRational(minutes, 1), IFDRational(micro, SECONDS_DENOMINATOR)


def gps_ifd(position: GPSPosition) -> dict:
    """The EXIF GPS IFD (tag -> value) of ``position``."""
    tags = {ExifTags.GPS.GPSVersionID: b"\x02\x03\x00\x00",
            ExifTags.GPS.GPSLatitudeRef: "N" if position.latitude >= 0 else "S",
            ExifTags.GPS.GPSLatitude: _dms(position.latitude),
            ExifTags.GPS.GPSLongitudeRef: "E" if position.longitude >= 0 else "W",
            ExifTags.GPS.GPSLongitude: _dms(position.longitude)}
    if position.altitude is not None:
        tags[ExifTags.GPS.GPSAltitudeRef] = b"\x00" if position.altitude >= 0 else b"\x01"
        tags[ExifTags.GPS.GPSAltitude] = IFDRational(round(abs(position.altitude) * ALTITUDE_DENOMINATOR),
                                                     ALTITUDE_DENOMINATOR)
    return tags


def _jpeg_with_exif(data: bytes, exif: bytes) -> bytes:
    """The JPEG ``data`` with its Exif APP1 segment replaced by ``exif`` (``Exif\\0\\0`` + TIFF), or inserted
    after SOI (and a JFIF APP0) when it has none; the entropy-coded data is kept byte for byte."""
    if data[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG file")
    if len(exif) + 2 > 0xFFFF:
        raise ValueError("Exif data too large for one APP1 segment")
    segment = b"\xff\xe1" + struct.pack(">H", len(exif) + 2) + exif
    pos, insert_at, dropped = 2, 2, []
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker in (0xDA, 0xD9):  # start of scan / end of image: the headers end here
            break
        length = struct.unpack(">H", data[pos + 2: pos + 4])[0]
        end = pos + 2 + length
        if marker == 0xE1 and data[pos + 4: pos + 10] == b"Exif\x00\x00":
            dropped.append((pos, end))  # the old Exif segment
        elif marker == 0xE0 and insert_at == pos:
            insert_at = end  # after JFIF APP0, as the standard asks
        pos = end
    out, cursor = bytearray(data[:insert_at]) + segment, insert_at
    for start, end in dropped:
        out += data[cursor:start]
        cursor = end
    return bytes(out + data[cursor:])


def write_gps(source: str | Path, target: str | Path, position: GPSPosition) -> Path:
    """Copy the photo ``source`` to ``target`` with ``position`` in its EXIF GPS tags (other EXIF kept).

    JPEG: the pixels are not re-encoded (only the Exif segment changes); other formats are
    re-saved by PIL. Returns ``target``, written atomically.
    """
    source, target = Path(source), Path(target)
    with Image.open(source) as image:
        exif = image.getexif()
        exif[GPS_IFD] = gps_ifd(position)
        if image.format == "JPEG":
            return write_atomic(target, _jpeg_with_exif(source.read_bytes(), exif.tobytes()))
        image.load()
        target.parent.mkdir(parents=True, exist_ok=True)
        image.save(target, format=image.format, exif=exif)
    return target
