"""The shared samplers (sekd_sfm/evaluation/samplers.py): their seeds reproduce, their draws keep their order.

Training runs resume from their seeds and the benchmarks regenerate their photos from them, so
the pinned numbers below are behaviour: a sampler that draws in another order, or once more or
less, changes them (the value drawn next from the generator counts the draws).
"""
import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from sekd_sfm.evaluation import samplers

EVALUATION = Path(samplers.__file__).parent

#: name -> (sampler drawing from default_rng(7), expected matrix, the generator's next random()).
GEOMETRIC = {
    "training affine": (
        lambda rng: samplers.random_affine(rng, (-40, 40), (-40, 40), (0.7, 1.4), (-0.04, 0.04), False),
        [[1.2240675425082876, -0.5714779741317381, -0.015986697207101965],
         [0.21600437482393706, 0.6395060028651482, 0.02988427563170095]], 0.005265304565574724),
    "training warp, isotropic, projective": (
        lambda rng: samplers.random_warp(rng, (-40, 40), (-40, 40), (0.7, 1.4), (-0.04, 0.04), True, 0.1),
        [[1.2240675425082876, -0.8282397207968004, -0.021983424800752653],
         [0.21600437482393706, 0.926832349165585, -0.015986697207101965],
         [0.07471068907925238, -0.09894693908688507, 1.0]], 0.8212284183827663),
    "localisation benchmark": (
        lambda rng: samplers.random_centred_homography(rng, 640, 480, 15.0, (0.85, 1.15), 2e-4),
        [[1.1624063510006943, -0.1094006430465603, -23.039437956451273],
         [0.10061472769453392, 1.1001842193831857, -53.706962328161346],
         [0.0001112653902069779, -0.00011090502813031586, 1.0]], 0.005265304565574724),
    "distillation window": (
        lambda rng: samplers.random_window_homography(rng, (120, 160), (64, 96), (0.5, 1.0), 0.15, 20.0),
        [[1.1291304713692982, 0.37354030136266814, 16.75149917602539],
         [-0.3325383773634658, 1.3623121646097045, 43.40382766723633],
         [-0.002110479505789723, 0.0012252003959643527, 1.0]], 0.2548695876541246),
    "distillation view change": (
        lambda rng: samplers.random_view_change(rng, (64, 96), (0.7, 1.4), 0.3, 30.0),
        [[0.516016629432357, -0.18218302986227713, 24.79783821105957],
         [-0.18619781652107906, 0.438825882749993, 13.427874565124512],
         [-0.00010938299273620019, -0.006626203410628123, 1.0]], 0.3030324268193135),
}


@pytest.mark.parametrize("name", GEOMETRIC)
def test_geometric_samplers_reproduce_their_seeds(name):
    sampler, expected, next_draw = GEOMETRIC[name]
    rng = np.random.default_rng(7)
    assert np.allclose(sampler(rng), expected, rtol=1e-12, atol=1e-15)
    assert rng.random() == next_draw


#: seed -> (jitter_gray of GRAY_RAMP in grey levels, next random()); the seeds cover blur and noise.
GRAY_JITTER = {
    0: ([[64, 69, 82, 95, 101], [91, 96, 107, 120, 125], [140, 145, 155, 166, 170], [164, 169, 178, 188, 192]],
        0.6066357757671799),
    3: ([[0, 0, 0, 12, 6], [9, 15, 19, 24, 33], [43, 47, 59, 62, 71], [84, 88, 93, 102, 113]], 0.47130966518183137),
    5: ([[19, 32, 51, 68, 79], [89, 105, 128, 139, 148], [169, 181, 198, 214, 229], [249, 255, 253, 255, 255]],
        0.2273185251609081),
}
GRAY_RAMP = (np.arange(20).reshape(4, 5) * 12 % 256).astype(np.float64) / 255


@pytest.mark.parametrize("seed", GRAY_JITTER)
def test_gray_jitter_reproduces_its_seeds_in_8_bit_levels(seed):
    expected, next_draw = GRAY_JITTER[seed]
    rng = np.random.default_rng(seed)
    out = samplers.jitter_gray(GRAY_RAMP, rng)
    assert out.dtype == np.float64 and np.array_equal(out * 255, np.round(out * 255))  # 8-bit levels
    assert np.round(out * 255).astype(int).tolist() == expected
    assert rng.random() == next_draw


def test_exposure_of_rendered_photos_reproduces_its_seed():
    image = (np.arange(24).reshape(2, 4, 3) * 10).astype(np.uint8)
    rng = np.random.default_rng(7)
    out = samplers.expose_u8(image, rng)
    assert out.dtype == np.uint8
    assert out.tolist() == [[[0, 4, 12], [19, 29, 40], [48, 56, 67], [78, 88, 98]],
                            [[110, 122, 131], [144, 153, 166], [177, 192, 202], [217, 229, 242]]]
    assert rng.random() == 0.4662060253252891


def test_colour_jitter_reproduces_its_seed():
    rgb = torch.from_numpy((np.arange(60).reshape(3, 4, 5) * 4 % 256).astype(np.float32))
    rng = np.random.default_rng(7)
    out = samplers.color_jitter(rgb, rng, (0.6, 1.4), (0.6, 1.4), (0.6, 1.4), (-0.2, 0.2))
    assert out[0].int().tolist() == [[86, 90, 94, 97, 101], [105, 109, 112, 116, 121], [124, 127, 131, 133, 135],
                                     [136, 137, 137, 138, 139]]
    assert out[2, 3].int().tolist() == [212, 213, 213, 214, 215]
    assert rng.random() == 0.005265304565574724


def test_identity_colour_jitter_draws_everything_and_changes_nothing():
    rgb = torch.from_numpy((np.arange(60).reshape(3, 4, 5) * 4 % 256).astype(np.float32))
    rng = np.random.default_rng(7)
    out = samplers.color_jitter(rgb, rng, (1, 1), (1, 1), (1, 1), (0, 0))
    assert torch.equal(out, rgb)
    assert rng.random() == 0.005265304565574724  # the same stream as the jitter above


def test_projective_terms_are_drawn_only_when_asked_in_training_and_always_in_the_benchmark():
    def draws_after(sampler) -> float:
        rng = np.random.default_rng(3)
        sampler(rng)
        return rng.random()

    reference = np.random.default_rng(3)
    reference.random(6)  # rotation, shear, sx, sy, tx, ty
    affine_only = samplers.random_warp(np.random.default_rng(3), (-1, 1), (0, 0), (1, 1), (0, 0), False, 0.0)
    assert affine_only.shape == (2, 3)
    assert draws_after(lambda rng: samplers.random_warp(rng, (-1, 1), (0, 0), (1, 1), (0, 0), False, 0.0)) \
        == reference.random()
    reference = np.random.default_rng(3)
    reference.random(6)  # angle, scale, g, h (drawn although 0), shift x, y
    assert draws_after(lambda rng: samplers.random_centred_homography(rng, 64, 48, 10, (1, 1), 0.0)) \
        == reference.random()


def test_affine_matrix_rotates_scales_shears_and_shifts():
    quarter = samplers.affine_matrix(np.pi / 2, 2.0, 3.0, shift=(0.5, -0.5))
    assert np.allclose(quarter @ [1, 0, 1], [0.5, 1.5])   # x scaled by 2, turned onto +y, shifted
    assert np.allclose(quarter @ [0, 1, 1], [-2.5, -0.5])  # y scaled by 3, turned onto -x
    sheared = samplers.affine_matrix(0.0, 1.0, 1.0, shear=np.pi / 4)
    assert np.allclose(sheared @ [0, 1, 0], [-np.sqrt(0.5), np.sqrt(0.5)])
    assert np.array_equal(samplers.homography_of(quarter, (0.1, 0.2))[2], [0.1, 0.2, 1.0])


def test_window_homography_without_distortion_is_a_scaled_crop_inside_the_image():
    # Crop scale 0.5: the 48 x 32 crop covers a 96 x 64 px window of the photo.
    rng = np.random.default_rng(0)
    crop_to_image = samplers.random_window_homography(rng, (120, 160), (32, 48), (0.5, 0.5), 0.0, 0.0)
    corners = np.array([[0, 0, 1], [47, 0, 1], [47, 31, 1], [0, 31, 1]], float) @ crop_to_image.T
    xy = corners[:, :2] / corners[:, 2:]
    assert np.allclose(xy[1] - xy[0], [96, 0], atol=1e-3) and np.allclose(xy[3] - xy[0], [0, 64], atol=1e-3)
    assert (xy >= -1e-3).all() and (xy[:, 0] <= 160 + 1e-3).all() and (xy[:, 1] <= 120 + 1e-3).all()


def test_evaluation_imports_neither_bench_nor_train():
    for path in EVALUATION.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                target = ("." * node.level) + (node.module or "")
                assert not target.startswith(("..bench", "..train", "sekd_sfm.bench", "sekd_sfm.train")), \
                    f"{path.name} imports {target}"


def test_samplers_load_without_torch():
    """bench/scale's pycolmap baseline imports the samplers in processes whose memory is measured."""
    code = "import sys, sekd_sfm.evaluation.samplers, sekd_sfm.bench.scale.run; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
