"""Keyframes: the frames of a video worth mapping, written as photos.

    videos -> images/<video>/<frame>.jpg + images/keyframes.json

A video holds far more frames than a model needs, many of them nearly identical (the camera
barely moved) and some motion-blurred. The frames are decoded as a stream (``files.video``);
at most ``max_fps`` per second are looked at, each reduced to ``analysis_size`` px:

* **sharpness**: the variance of its Laplacian. A frame under ``blur_ratio`` times the median of
  the last ``blur_window`` frames looked at is blurred and never a keyframe (motion blur wipes
  out the fine texture keypoints live on; the median follows the scene's own texture).
* **motion** (``count`` None, the default): corners of the last keyframe tracked into the frame
  (pyramidal Lucas-Kanade). A sharp frame becomes the next keyframe once the median corner
  moved ``min_motion`` of the long side, or fewer than half the corners can be followed (the
  view changed): enough parallax to the previous keyframe, and no run of near-identical frames.
* **a fixed count** (``count`` N): the video cut into N equal spans of time, the sharpest frame
  of each (spans whose frames are all blurred give none).

Keyframes are written as ``<video>/<frame:06d>.jpg`` below the image folder, each JPEG's EXIF
naming its video (one COLMAP camera per video), with ``keyframes.json``; names, record, resuming
and errors: docs/captures.md.
"""
from __future__ import annotations

import io
import json
import logging
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import SekdError
from ..files.atomic import write_atomic
from ..files.video import VideoReader, list_videos

logger = logging.getLogger("sekd")

RECORD = "keyframes.json"
#: A frame with fewer corners is featureless: never a keyframe (nothing to map, no motion to measure).
MIN_CORNERS = 8
FORMAT = "sekd-keyframes/1"


@dataclass
class KeyframeConfig:
    """How keyframes are chosen (module doc). ``count``: None for keyframes by motion, N for N per video."""

    count: int | None = None
    #: Frames looked at per second, at most (a 60 fps video is looked at 10 times a second).
    max_fps: float = 10.0
    #: Median motion (share of the long side) since the last keyframe that makes the next one.
    #: 10 %: 64 px at 640 px, a tenth of the view new (5 % kept 147 keyframes of a generated 20 s walk at 7.5 m/s,
    #: a frame looked at in two).
    min_motion: float = 0.1
    #: A frame whose sharpness is under this share of the recent median is blurred.
    blur_ratio: float = 0.5
    #: Frames looked at (half a second at 10 a second) whose median sharpness a frame is compared with: short, so that
    #: a scene turning from a textured facade to a plain one (sharpness falling 10x in 1.5 s) is not taken for blur.
    blur_window: int = 5
    #: Long side (px) frames are analysed at (the keyframes are written at full size).
    analysis_size: int = 480
    jpeg_quality: int = 95


@dataclass
class Keyframe:
    """One keyframe: its file name (below the image folder), frame index, time (s) and sharpness."""

    name: str
    frame: int
    time_s: float
    sharpness: float


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian of ``gray`` (H x W uint8): high for sharp texture, low when blurred."""
    import cv2

    return float(cv2.Laplacian(gray, cv2.CV_32F).var())


def analysis_image(frame: np.ndarray, size: int) -> np.ndarray:
    """``frame`` (BGR) as grey, its long side reduced to ``size`` px."""
    import cv2

    gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    scale = size / max(gray.shape)
    return cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else gray


class MotionTracker:
    """Image motion since the last keyframe: its corners followed into later frames."""

    def __init__(self) -> None:
        self.reference: np.ndarray | None = None
        self.corners: np.ndarray | None = None

    @staticmethod
    def corners_of(gray: np.ndarray) -> np.ndarray:
        """Up to 300 corners of ``gray`` (N x 1 x 2, float32; N = 0 on a featureless frame)."""
        import cv2

        found = cv2.goodFeaturesToTrack(gray, maxCorners=300, qualityLevel=0.01, minDistance=8)
        return found if found is not None else np.zeros((0, 1, 2), np.float32)

    def reset(self, gray: np.ndarray, corners: np.ndarray) -> None:
        self.reference, self.corners = gray, corners

    def motion(self, gray: np.ndarray) -> tuple[float, float]:
        """(median corner motion as a share of the long side, share of the corners followed)."""
        import cv2

        if self.corners is None or len(self.corners) < MIN_CORNERS:
            return 0.0, 0.0
        moved, status, _ = cv2.calcOpticalFlowPyrLK(self.reference, gray, self.corners, None, winSize=(21, 21),
                                                    maxLevel=4)
        found = status.ravel() == 1
        if not found.any():
            return 0.0, 0.0
        shift = np.linalg.norm((moved - self.corners).reshape(-1, 2)[found], axis=1)
        return float(np.median(shift)) / max(gray.shape), float(found.mean())


def video_name(video: Path, root: Path) -> str:
    """The keyframes' folder of ``video``: its path below ``root`` (the input folder) without the extension."""
    relative = video.relative_to(root) if root.is_dir() else Path(video.name)
    return relative.with_suffix("").as_posix()


def _signature(video: Path) -> dict:
    stat = video.stat()
    return {"bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns}


def _write_jpeg(frame: np.ndarray, path: Path, video: str, index: int, time_s: float, quality: int) -> None:
    """``frame`` (BGR) as a JPEG whose EXIF names its video (one camera per video), written atomically."""
    from PIL import Image

    image = Image.fromarray(np.ascontiguousarray(frame[:, :, ::-1]))
    exif = Image.Exif()
    exif[0x010F] = "sekd keyframe"  # Make
    exif[0x0110] = video  # Model: COLMAP's camera key tells videos apart by it
    exif[0x010E] = f"{video} frame {index} at {time_s:.3f} s"  # ImageDescription
    buffer = io.BytesIO()
    image.save(buffer, format="JPEG", quality=quality, exif=exif)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, buffer.getvalue(), durable=False)


def _is_blurred(value: float, history: deque, config: KeyframeConfig) -> bool:
    return len(history) >= 3 and value < config.blur_ratio * float(np.median(history))


def select_keyframes(reader: VideoReader, name: str, config: KeyframeConfig, write, progress=None) -> dict:
    """Stream ``reader``'s frames, choose keyframes (module doc) and hand each to ``write(frame, keyframe)``.
    Returns the video's record."""
    step = 1.0 / config.max_fps if config.max_fps and reader.fps > 0 else 0.0
    history: deque = deque(maxlen=config.blur_window)
    tracker = MotionTracker()
    keyframes: list[Keyframe] = []
    looked = blurred = 0
    next_time = 0.0
    spans = config.count
    if spans is not None and reader.frame_count <= 0:
        raise SekdError(f"{reader.path}: the video does not say how many frames it has; --keyframes {spans} needs "
                        "that: use --keyframes auto")
    best: tuple[float, int, float, np.ndarray] | None = None  # sharpest frame of the current span
    span = 0
    for index, time_s, frame in reader:
        if progress is not None:
            progress(1)
        if step and time_s + 1e-9 < next_time:
            continue
        next_time = time_s + step if step else 0.0
        gray = analysis_image(frame, config.analysis_size)
        value = sharpness(gray)
        is_blurred = _is_blurred(value, history, config)
        history.append(value)
        looked += 1
        blurred += is_blurred
        if spans is not None:
            here = min(spans - 1, index * spans // reader.frame_count)
            if here != span and best is not None:
                keyframes.append(_take(best, name, write))
                best = None
            span = here
            if not is_blurred and (best is None or value > best[0]):
                best = (value, index, time_s, frame.copy())
            continue
        if is_blurred:
            continue
        if tracker.reference is not None:
            moved, followed = tracker.motion(gray)
            if moved < config.min_motion and followed >= 0.5:
                continue
        corners = tracker.corners_of(gray)
        if len(corners) < MIN_CORNERS:  # featureless (a blank wall, a covered lens): nothing to map or track
            continue
        keyframes.append(_take((value, index, time_s, frame), name, write))
        tracker.reset(gray, corners)
    if best is not None:
        keyframes.append(_take(best, name, write))
    return {"size": list(reader.size), "fps": reader.fps, "frame_count": reader.frame_count,
            "frames_read": index + 1, "frames_looked_at": looked, "blurred_skipped": blurred,
            "broken_at_frame": reader.broken, "keyframes": [asdict(k) for k in keyframes]}


def _take(candidate: tuple[float, int, float, np.ndarray], name: str, write) -> Keyframe:
    value, index, time_s, frame = candidate
    keyframe = Keyframe(f"{name}/{index:06d}.jpg", index, round(time_s, 4), round(value, 2))
    write(frame, keyframe)
    return keyframe


def extract_keyframes(source: str | Path, image_dir: str | Path, config: KeyframeConfig | None = None,
                      progress: bool = True) -> dict:
    """The keyframes of every video of ``source`` (a video file, or a folder: the videos below it) written below
    ``image_dir`` (module doc); returns the record also written to ``image_dir/keyframes.json``."""
    from tqdm import tqdm

    source, image_dir = Path(source), Path(image_dir)
    config = config or KeyframeConfig()
    videos = list_videos(source)
    if not videos:
        raise SekdError(f"{source}: no video found")
    image_dir.mkdir(parents=True, exist_ok=True)
    record_path = image_dir / RECORD
    record = _read_record(record_path, config)
    for video in videos:
        name = video_name(video, source)
        done = record["videos"].get(name)
        if done and done.get("source") == _signature(video) and all(
                (image_dir / k["name"]).is_file() for k in done["keyframes"]):
            continue
        with VideoReader(video) as reader:
            bar = tqdm(total=reader.frame_count or None, desc=f"keyframes {name}", unit="frame", disable=not progress,
                       leave=False)

            def write(frame, keyframe: Keyframe) -> None:
                _write_jpeg(frame, image_dir / keyframe.name, name, keyframe.frame, keyframe.time_s,
                            config.jpeg_quality)

            entry = select_keyframes(reader, name, config, write, bar.update)
            bar.close()
        entry["source"] = _signature(video)
        entry["path"] = str(video.resolve())
        record["videos"][name] = entry
        write_atomic(record_path, json.dumps(record, indent=1))
        if entry["broken_at_frame"] is not None:
            logger.warning("warning: %s: could not decode frame %d of %d; the %d keyframes before it are kept",
                           video, entry["broken_at_frame"], entry["frame_count"], len(entry["keyframes"]))
        logger.info("%s: %d keyframes of %d frames (%d blurred frames skipped)", video, len(entry["keyframes"]),
                    entry["frames_read"], entry["blurred_skipped"])
    return record


def _read_record(path: Path, config: KeyframeConfig) -> dict:
    """The keyframes record in ``path`` when it was made with ``config``, else a new one."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        record = None
    if isinstance(record, dict) and record.get("format") == FORMAT and record.get("config") == asdict(config):
        return record
    for entry in (record or {}).get("videos", {}).values() if isinstance(record, dict) else ():
        for keyframe in entry.get("keyframes", []):  # chosen under other settings: not photos of this run
            (path.parent / keyframe["name"]).unlink(missing_ok=True)
    return {"format": FORMAT, "config": asdict(config), "videos": {}}


def prepare_captures(source: str | Path, image_dir: str | Path, config: KeyframeConfig | None = None,
                     progress: bool = True) -> dict:
    """``image_dir`` made the photo folder of ``source`` (a video, or a folder of videos and photos): its videos'
    keyframes (``extract_keyframes``) and its photos (``link_photos``). Returns the keyframes record."""
    made = extract_keyframes(source, image_dir, config, progress)
    link_photos(source, image_dir)
    return made


def link_photos(source: str | Path, image_dir: str | Path, exclude: set[str] = frozenset()) -> list[str]:
    """The photos of ``source`` (a folder that also holds videos) linked into ``image_dir`` under their relative
    names (a symbolic link, a copy where links cannot be made), but those named in ``exclude``; returns their
    names. A video file: none."""
    import shutil

    from ..files.images import IMAGE_EXTENSIONS

    source, image_dir = Path(source), Path(image_dir)
    if not source.is_dir():
        return []
    names = []
    for path in sorted(source.rglob("*")):
        if path.suffix.lower() not in IMAGE_EXTENSIONS or not path.is_file():
            continue
        name = path.relative_to(source).as_posix()
        if name in exclude:
            continue
        target = image_dir / name
        names.append(name)
        if target.is_symlink() or target.exists():
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            target.symlink_to(path.resolve())
        except OSError:
            shutil.copy2(path, target)
    return names
