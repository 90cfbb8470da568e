"""Fuzzing the inputs (#16): 200 random byte strings as images and as feature files never produce a
traceback: every command ends with exit code 0 (bad files skipped with a warning) or 1 (one `Error:` line)."""
from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sekd_sfm.cli.main import sekd
from sekd_sfm.files import features as ff

COUNT = 200
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def random_bytes(rng: np.random.Generator, prefixes: list[bytes]) -> bytes:
    """Random bytes, half of them behind a real magic number so decoders get past the first check."""
    body = rng.integers(0, 256, int(rng.integers(0, 3000)), dtype=np.uint8).tobytes()
    return (prefixes[int(rng.integers(len(prefixes)))] if rng.random() < 0.5 else b"") + body


def png_header(rng: np.random.Generator) -> bytes:
    """A PNG signature and IHDR with random size (up to 2^31 px a side), depth and colour type."""
    width, height = (int(v) for v in rng.integers(1, 2**31, 2))
    ihdr = struct.pack(">IIBBBBB", width, height, int(rng.choice([1, 8, 16])), int(rng.choice([0, 2, 6])), 0, 0, 0)
    return PNG_SIGNATURE + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))


def run(*args):
    return CliRunner().invoke(sekd, ["-q", *map(str, args)])


def assert_clean_exit(result, what: str) -> None:
    """Exit 0, or exit 1 with exactly one `Error:` line; never a traceback or an uncaught exception."""
    assert isinstance(result.exception, (SystemExit, type(None))), (what, repr(result.exception), result.output)
    assert "Traceback" not in result.output, (what, result.output)
    if result.exit_code != 0:
        assert result.exit_code == 1, (what, result.output)
        assert sum(line.startswith("Error:") for line in result.output.splitlines()) == 1, (what, result.output)


def test_random_bytes_as_images(tmp_path):
    rng = np.random.default_rng(16)
    folder = tmp_path / "images"
    folder.mkdir()
    cv2.imwrite(str(folder / "good.png"), (rng.random((64, 80)) * 255).astype(np.uint8))
    names = []
    for i in range(COUNT):
        ext = (".jpg", ".png")[i % 2]
        prefix = [b"\xff\xd8\xff\xe0", b"\xff\xd8\xff\xe0\x00\x00", b"\xff\xd8\xff\xc0\x00\x11\x08\xff\xff\xff\xff",
                  png_header(rng)]
        (folder / f"{i:03d}{ext}").write_bytes(random_bytes(rng, prefix))
        names.append(f"{i:03d}{ext}")
    out = tmp_path / "f.h5"
    result = run("extract", folder, "-o", out, "--feature", "sift", "--max-keypoints", 50, "--no-progress")
    assert_clean_exit(result, "extract")
    assert result.exit_code == 0, result.output
    keys = ff.list_keys(out)
    failed = json.loads(ff.read_attrs(out)["failed_images"])
    assert "good.png" in keys and sorted(keys + failed) == sorted(names + ["good.png"])
    assert len(failed) >= COUNT - 5  # random bytes almost never decode
    # --strict stops at the first bad image with one line.
    assert_clean_exit(run("extract", folder, "-o", tmp_path / "g.h5", "--feature", "sift", "--strict", "--no-progress"),
                      "extract --strict")


@pytest.fixture(scope="module")
def valid_features(tmp_path_factory) -> tuple[Path, Path]:
    """A real 3-image SIFT feature file and its exhaustive pairs file."""
    root = tmp_path_factory.mktemp("fuzz")
    rng = np.random.default_rng(0)
    (root / "img").mkdir()
    for i in range(3):
        image = cv2.GaussianBlur((rng.random((96, 128)) * 255).astype(np.uint8), (0, 0), 2)
        cv2.imwrite(str(root / "img" / f"{i}.png"), image)
    features, pairs = root / "valid.h5", root / "pairs.txt"
    assert run("extract", root / "img", "-o", features, "--feature", "sift", "--max-keypoints", 40,
               "--no-progress").exit_code == 0
    assert run("pairs", features, "-o", pairs).exit_code == 0
    return features, pairs


def corrupted(rng: np.random.Generator, valid: bytes) -> bytes:
    """``valid`` with a few random bytes overwritten, or truncated at a random point."""
    data = bytearray(valid)
    if rng.random() < 0.3:
        return bytes(data[: int(rng.integers(0, len(data)))])
    for position in rng.integers(0, len(data), int(rng.integers(1, 20))):
        data[int(position)] = int(rng.integers(0, 256))
    return bytes(data)


def test_random_bytes_as_feature_files(tmp_path, valid_features):
    features, pairs = valid_features
    valid = features.read_bytes()
    rng = np.random.default_rng(17)
    outcomes = {0: 0, 1: 0}
    for i in range(COUNT):
        path = tmp_path / f"{i:03d}.h5"
        path.write_bytes(random_bytes(rng, [HDF5_SIGNATURE]) if i % 2 else corrupted(rng, valid))
        for args in (["pairs", path, "-o", tmp_path / f"{i:03d}.txt"],
                     ["match", path, pairs, "-o", tmp_path / f"{i:03d}-m.h5", "--no-progress"]):
            result = run(*args)
            assert_clean_exit(result, f"{args[0]} on fuzz file {i}")
            outcomes[result.exit_code] += 1
    assert outcomes[1] >= COUNT  # every random file and most corrupted ones are refused
