"""Video files: which files are videos, and their frames decoded as a stream (OpenCV's FFmpeg backend).

Frames are read one at a time and never held together: a 4K phone video of ten minutes is
decoded in the memory of one frame. A file that OpenCV cannot open, or whose first frame it
cannot decode (a codec its FFmpeg lacks), is a SekdError naming the file; a file that breaks
part way (truncated, damaged) yields the frames before the damage, and ``VideoReader.broken``
says where it stopped.
"""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import SekdError

#: Extensions read as videos (any case).
VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv", ".mts", ".m2ts", ".3gp")


def is_video(path: str | Path) -> bool:
    """Whether ``path`` is a file with a video extension."""
    path = Path(path)
    return path.suffix.lower() in VIDEO_EXTENSIONS and path.is_file()


def list_videos(root: str | Path) -> list[Path]:
    """The videos of ``root``: itself when it is a video file, else those below the folder (recursive), sorted."""
    root = Path(root)
    if root.is_file():
        return [root] if is_video(root) else []
    if not root.is_dir():
        return []
    return sorted(p for p in root.rglob("*") if p.suffix.lower() in VIDEO_EXTENSIONS and p.is_file())


def _quiet_opencv() -> None:
    """OpenCV's own warnings (e.g. FFmpeg failing to open a file) off: our error says it in one line."""
    import cv2

    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    except AttributeError:  # builds without the logging module
        pass


class VideoReader:
    """One video, opened for streaming. ``fps`` (frames per second; 0 when the file does not say), ``frame_count``
    (what the container claims; 0 when unknown), ``size`` (width, height). Iterating yields
    ``(index, time_s, frame)``: the frame's 0-based index, its time from the start (s), the BGR uint8 frame
    (H x W x 3)."""

    def __init__(self, path: str | Path):
        import cv2

        _quiet_opencv()
        self.path = Path(path)
        self.broken: int | None = None  # index of the first frame that could not be decoded, if the video broke
        self._capture = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG)
        if not self._capture.isOpened():
            raise SekdError(f"{self.path}: cannot open this video (not a video, or a format OpenCV's FFmpeg cannot "
                            "read); convert it, e.g. ffmpeg -i IN -c:v libx264 OUT.mp4")
        self.fps = float(self._capture.get(cv2.CAP_PROP_FPS) or 0.0)
        self.frame_count = max(0, int(self._capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0))
        ok, first = self._capture.read()
        if not ok or first is None:
            self._capture.release()
            raise SekdError(f"{self.path}: cannot decode its first frame (a codec OpenCV's FFmpeg lacks, or an "
                            "empty or damaged file); convert it, e.g. ffmpeg -i IN -c:v libx264 OUT.mp4")
        self._first: np.ndarray | None = first
        self.size = (int(first.shape[1]), int(first.shape[0]))

    def time_of(self, index: int) -> float:
        """Seconds from the start of frame ``index`` (at the container's frame rate; 0 when unknown)."""
        return index / self.fps if self.fps > 0 else 0.0

    def __iter__(self) -> Iterator[tuple[int, float, np.ndarray]]:
        if self._first is None:
            raise SekdError(f"{self.path}: a video is read once; open it again")
        frame, index = self._first, 0
        self._first = None
        while frame is not None:
            yield index, self.time_of(index), frame
            ok, frame = self._capture.read()
            index += 1
            if not ok:
                if self.frame_count and index < self.frame_count:
                    self.broken = index  # the container promised more: damaged or truncated here
                frame = None
        self.close()

    def close(self) -> None:
        self._capture.release()

    def __enter__(self) -> VideoReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
