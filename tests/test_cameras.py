"""Camera grouping of --camera-mode auto: image size and EXIF make, model, focal length (hand-made EXIF)."""
from pathlib import Path

import pytest
from PIL import Image

from sekd_sfm.errors import SekdError
from sekd_sfm.stages.colmap import open_database, require_pycolmap
from sekd_sfm.stages.database import (
    PRINCIPAL_POINT_MIN_IMAGES,
    CameraConfig,
    _import_images,
    camera_groups,
    camera_key,
    images_per_camera,
    refines_principal_point,
    tries_principal_point,
)
from sekd_sfm.stages.mapping import default_options, set_principal_point_refinement

pycolmap = require_pycolmap()
EXIF_IFD, FOCAL, MAKE, MODEL = 0x8769, 0x920A, 0x010F, 0x0110


def photo(path: Path, size=(64, 48), make=None, model=None, focal=None) -> Path:
    """A small JPEG with the given EXIF fields (None = absent)."""
    exif = Image.Exif()
    if make is not None:
        exif[MAKE] = make
    if model is not None:
        exif[MODEL] = model
    if focal is not None:
        exif.get_ifd(EXIF_IFD)[FOCAL] = focal
    Image.new("RGB", size, (90, 120, 150)).save(path, exif=exif)
    return path


@pytest.fixture
def folder(tmp_path):
    """Photos: a-c one camera (same EXIF), d another focal length, e another model,
    f-g no EXIF, h no EXIF at another size."""
    canon = {"make": "Canon", "model": "EOS 5D"}
    photo(tmp_path / "a.jpg", **canon, focal=35.0)
    photo(tmp_path / "b.jpg", **canon, focal=35.0)
    photo(tmp_path / "c.jpg", **canon, focal=35.0)
    photo(tmp_path / "d.jpg", **canon, focal=50.0)
    photo(tmp_path / "e.jpg", make="Canon", model="EOS 6D", focal=35.0)
    photo(tmp_path / "f.jpg")
    photo(tmp_path / "g.jpg")
    photo(tmp_path / "h.jpg", size=(48, 64))
    return tmp_path


def test_camera_key_reads_size_and_exif(folder):
    assert camera_key(folder / "a.jpg") == (64, 48, "canon", "eos 5d", 35.0)
    assert camera_key(folder / "f.jpg") == (64, 48, None, None, None)
    (folder / "broken.jpg").write_bytes(b"not an image")
    assert camera_key(folder / "broken.jpg") == (str(folder / "broken.jpg"),)  # its own camera


def test_groups_by_size_and_exif(folder):
    names = sorted(p.name for p in folder.glob("*.jpg"))
    assert camera_groups(folder, names) == [["a.jpg", "b.jpg", "c.jpg"], ["d.jpg"], ["e.jpg"],
                                            # no EXIF and the same size: taken to be one camera
                                            ["f.jpg", "g.jpg"], ["h.jpg"]]
    assert camera_groups(folder, []) == []


def cameras_of(database: Path) -> dict[str, int]:
    with open_database(database) as db:
        return {image.name: image.camera_id for image in db.read_all_images()}


def test_auto_mode_shares_cameras_in_the_database(folder, tmp_path_factory):
    names = sorted(p.name for p in folder.glob("*.jpg"))
    database = tmp_path_factory.mktemp("db") / "database.db"
    _import_images(database, folder, names, CameraConfig(mode="auto"))
    ids = cameras_of(database)
    assert len(set(ids.values())) == 5
    assert ids["a.jpg"] == ids["b.jpg"] == ids["c.jpg"] and ids["f.jpg"] == ids["g.jpg"]
    assert len({ids["a.jpg"], ids["d.jpg"], ids["e.jpg"], ids["f.jpg"], ids["h.jpg"]}) == 5


def test_images_per_camera_counts_the_auto_groups(folder, tmp_path_factory):
    database = tmp_path_factory.mktemp("db") / "database.db"
    _import_images(database, folder, sorted(p.name for p in folder.glob("*.jpg")), CameraConfig(mode="auto"))
    assert images_per_camera(database) == [1, 1, 1, 2, 3]  # d, e, h alone; f-g; a-c


@pytest.mark.parametrize("setting, params, per_camera, refined, tested", [
    # auto: the mapper keeps it fixed; a final adjustment refines it, kept where the photos determine it
    ("auto", None, [11], False, True),                                   # fountain-P11: one camera, 11 photos
    ("auto", None, [PRINCIPAL_POINT_MIN_IMAGES] * 3, False, True),
    ("auto", None, [40, PRINCIPAL_POINT_MIN_IMAGES - 1], False, False),  # one camera too few photos: all stay fixed
    ("auto", None, [1] * 10, False, False),                              # internet photos, one camera each
    ("auto", None, [], False, False),
    ("auto", "100,32,24", [50], False, False),                           # known intrinsics are kept
    ("refine", None, [1], True, False),                                  # refined from the start of mapping
    ("fixed", None, [50], False, False),
])
def test_principal_point_rule(setting, params, per_camera, refined, tested):
    camera = CameraConfig(params=params, principal_point=setting)
    assert refines_principal_point(camera, per_camera) is refined
    assert tries_principal_point(camera, per_camera) is tested


def test_unknown_principal_point_setting_is_an_error():
    with pytest.raises(SekdError, match="unknown principal-point setting 'free'; choose from auto, refine, fixed"):
        refines_principal_point(CameraConfig(principal_point="free"), [20])


def test_principal_point_setting_reaches_every_mapper():
    for kind, read in [("incremental", lambda o: o.ba_refine_principal_point),
                       ("hierarchical", lambda o: o.incremental_options.ba_refine_principal_point),
                       ("global", lambda o: o.mapper.bundle_adjustment.refine_principal_point)]:
        options = default_options(kind)
        assert read(options) is False  # COLMAP's default
        set_principal_point_refinement(options, True)
        assert read(options) is True, kind


def test_camera_params_still_win(folder, tmp_path_factory):
    names = ["a.jpg", "b.jpg", "d.jpg"]
    database = tmp_path_factory.mktemp("db") / "database.db"
    _import_images(database, folder, names, CameraConfig(model="SIMPLE_PINHOLE", mode="auto", params="100,32,24"))
    with open_database(database) as db:
        cameras = db.read_all_cameras()
    assert len(cameras) == 2 and all(c.params.tolist() == [100, 32, 24] and c.has_prior_focal_length
                                     for c in cameras)


def test_single_mode_with_two_sizes_is_one_clear_error(folder, tmp_path_factory):
    database = tmp_path_factory.mktemp("db") / "database.db"
    with pytest.raises(SekdError, match=r"COLMAP did not import 1 image\(s\): h.jpg; --camera-mode single needs "
                                        r"images of one size"):
        _import_images(database, folder, ["a.jpg", "h.jpg"], CameraConfig(mode="single"))


def test_fountain_is_one_camera(shared):
    images = shared / "data/sfm/fountain-P11/images"
    names = sorted(p.name for p in images.glob("*.jpg"))
    assert len(names) == 11 and camera_groups(images, names) == [names]
