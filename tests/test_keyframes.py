"""Videos as input (``sekd_sfm.files.video``, ``sekd_sfm.stages.keyframes``): keyframes by sharpness and motion."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from sekd_sfm.errors import SekdError
from sekd_sfm.files.video import VideoReader, list_videos
from sekd_sfm.stages.keyframes import KeyframeConfig, extract_keyframes

FPS, WIDTH, HEIGHT = 30, 320, 240


def write_pan(shared, path, frames: int = 120, blur_every: int = 7):
    """A camera panning across a COCO photo (2.7 px per frame), every ``blur_every``-th frame (3, 10, 17, ...)
    motion-blurred; Motion-JPEG AVI (every OpenCV build writes it). Returns the blurred frames' indices."""
    photo = cv2.imread(str(shared / "data/train/coco/000000000009.jpg"))
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (WIDTH, HEIGHT))
    blurred = set()
    kernel = np.full((1, 21), 1 / 21, np.float32)
    for i in range(frames):
        x = int(i * (photo.shape[1] - WIDTH) / frames)
        frame = photo[100:100 + HEIGHT, x:x + WIDTH].copy()
        if i % blur_every == 3:
            frame = cv2.filter2D(frame, -1, kernel)
            blurred.add(i)
        writer.write(frame)
    writer.release()
    return blurred


@pytest.fixture(scope="module")
def pan(shared, tmp_path_factory):
    root = tmp_path_factory.mktemp("video")
    blurred = write_pan(shared, root / "pan.avi")
    return root / "pan.avi", blurred


def test_the_reader_streams_every_frame(pan):
    video, _ = pan
    with VideoReader(video) as reader:
        assert reader.fps == FPS and reader.frame_count == 120 and reader.size == (WIDTH, HEIGHT)
        seen = [(index, time_s, frame.shape) for index, time_s, frame in reader]
    assert [i for i, _, _ in seen] == list(range(120)) and seen[30][1] == pytest.approx(1.0)
    assert seen[0][2] == (HEIGHT, WIDTH, 3) and reader.broken is None
    assert list_videos(video) == [video] and list_videos(video.parent) == [video]


def test_keyframes_skip_blurred_frames_and_follow_the_motion(pan, tmp_path):
    video, blurred = pan
    record = extract_keyframes(video, tmp_path / "images", progress=False)
    entry = record["videos"]["pan"]
    frames = [k["frame"] for k in entry["keyframes"]]
    assert not set(frames) & blurred and entry["blurred_skipped"] >= 4
    assert entry["frames_read"] == 120 and entry["frames_looked_at"] == 40  # 10 of 30 frames a second
    assert 6 <= len(frames) <= 15 and frames[0] == 0 and frames == sorted(frames)
    gaps = np.diff(frames)
    assert gaps.max() <= 18  # 2.7 px per frame: 10% of 320 px is 12 frames, 15-18 with a blurred one skipped
    first = entry["keyframes"][1]
    assert first["name"] == f"pan/{first['frame']:06d}.jpg" and first["time_s"] == pytest.approx(first["frame"] / FPS)
    names = sorted(p.relative_to(tmp_path / "images").as_posix() for p in (tmp_path / "images").rglob("*.jpg"))
    assert names == sorted(k["name"] for k in entry["keyframes"])
    with Image.open(tmp_path / "images" / first["name"]) as image:  # one camera per video: its EXIF model
        assert image.size == (WIDTH, HEIGHT) and image.getexif()[0x0110] == "pan"
    assert json.loads((tmp_path / "images" / "keyframes.json").read_text()) == record


def test_a_fixed_count_the_rerun_and_new_settings(pan, tmp_path):
    video, blurred = pan
    images = tmp_path / "images"
    record = extract_keyframes(video, images, KeyframeConfig(count=8), progress=False)
    frames = [k["frame"] for k in record["videos"]["pan"]["keyframes"]]
    assert len(frames) == 8 and not set(frames) & blurred
    assert [f * 8 // 120 for f in frames] == list(range(8))  # one per span of 15 frames
    stamps = {p: p.stat().st_mtime_ns for p in images.rglob("*.jpg")}
    assert extract_keyframes(video, images, KeyframeConfig(count=8), progress=False) == record  # not decoded again
    assert {p: p.stat().st_mtime_ns for p in images.rglob("*.jpg")} == stamps
    again = extract_keyframes(video, images, KeyframeConfig(count=4), progress=False)  # other settings
    assert len(list(images.rglob("*.jpg"))) == 4 == len(again["videos"]["pan"]["keyframes"])


def test_featureless_frames_are_never_keyframes(shared, tmp_path):
    """Half a second of a covered lens (flat grey) before the pan: no keyframe among those frames, and no run of
    them either (their motion cannot be measured)."""
    video = tmp_path / "covered.avi"
    write_pan(shared, tmp_path / "pan.avi", frames=60)
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (WIDTH, HEIGHT))
    for _ in range(15):
        writer.write(np.full((HEIGHT, WIDTH, 3), 128, np.uint8))
    with VideoReader(tmp_path / "pan.avi") as reader:
        for _, _, frame in reader:
            writer.write(frame)
    writer.release()
    record = extract_keyframes(video, tmp_path / "images", progress=False)
    frames = [k["frame"] for k in record["videos"]["covered"]["keyframes"]]
    assert frames and min(frames) >= 15


def test_a_truncated_video_keeps_the_frames_before_the_damage(pan, tmp_path, caplog):
    video, _ = pan
    cut = tmp_path / "cut.avi"
    cut.write_bytes(video.read_bytes()[: int(video.stat().st_size * 0.5)])
    record = extract_keyframes(cut, tmp_path / "images", progress=False)
    entry = record["videos"]["cut"]
    assert 30 <= entry["frames_read"] < 120 and entry["keyframes"]
    assert max(k["frame"] for k in entry["keyframes"]) < entry["frames_read"]
    if entry["broken_at_frame"] is not None:  # the container's frame count says where it broke
        assert "could not decode frame" in caplog.text


def test_what_is_not_a_video_is_one_error(tmp_path):
    fake = tmp_path / "clip.mp4"
    fake.write_text("not a video")
    with pytest.raises(SekdError, match=r"clip.mp4: cannot (open|decode)"):
        extract_keyframes(fake, tmp_path / "images", progress=False)
    with pytest.raises(SekdError, match="no video found"):
        extract_keyframes(tmp_path / "images", tmp_path / "other", progress=False)


def test_reconstruct_a_video_and_a_photo_beside_it(pan, shared, tmp_path):
    """`sekd reconstruct FOLDER` with a video and a photo: keyframes and the photo in OUTPUT/images, mapped."""
    from sekd_sfm.cli.main import sekd

    video, _ = pan
    folder = tmp_path / "capture"
    folder.mkdir()
    (folder / "pan.avi").symlink_to(video)
    (folder / "still.jpg").write_bytes((shared / "data/train/coco/000000000025.jpg").read_bytes())  # a stray
    out = tmp_path / "out"
    args = ["-q", "reconstruct", str(folder), "-o", str(out), "--feature", "sift", "--no-refine", "--keyframes",
            "10", "--no-progress"]
    result = CliRunner().invoke(sekd, args)
    assert result.exit_code == 0, result.output
    stats = json.loads((out / "stats.json").read_text())
    assert stats["images_dir"] == str(out / "images") and stats["keyframes"]["pan"]["keyframes"] == 10
    assert stats["config"]["pairs"]["mode"] == "sequential" and stats["config"]["pairs"]["num_neighbors"] == 10
    assert stats["model"]["registered_images"] >= 8 and "keyframes" in stats["timings_s"]
    assert (out / "images" / "still.jpg").is_file() and stats["matches"]["images"] == 11
    assert [u["name"] for u in stats["unregistered"]] == ["still.jpg"]
    bad = CliRunner().invoke(sekd, ["reconstruct", str(folder), "-o", str(out), "--keyframes", "1"])
    assert bad.exit_code == 2 and "give auto or a number of keyframes per video" in bad.output


def test_extract_a_video(pan, tmp_path):
    """`sekd extract VIDEO -o OUT/features.h5`: keyframes in OUT/images, their features keyed <video>/<frame>.jpg."""
    from sekd_sfm.cli.main import sekd
    from sekd_sfm.files.features import list_keys

    video, _ = pan
    out = tmp_path / "out" / "features.h5"
    result = CliRunner().invoke(sekd, ["-q", "extract", str(video), "-o", str(out), "--feature", "sift",
                                       "--keyframes", "5", "--no-progress"])
    assert result.exit_code == 0, result.output
    record = json.loads((tmp_path / "out" / "images" / "keyframes.json").read_text())
    assert list_keys(out) == [k["name"] for k in record["videos"]["pan"]["keyframes"]]
