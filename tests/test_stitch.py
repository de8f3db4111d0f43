"""Stitching: design homographies, feathered warps, refinement from images, FER from coverage."""

import numpy as np
import pytest
import torch

from hbis_torch.design import design
from hbis_torch.errors import HbisInputError
from hbis_torch.registration import apply_homography
from hbis_torch.simulate import SensorModel
from hbis_torch.system.array.cameras import CAMERA_NAMES, CameraArray
from hbis_torch.system.array.render import ArrayRenderer
from hbis_torch.system.array.scenario import default_scene
from hbis_torch.system.array.sensor import periphery_sensor
from hbis_torch.system.stitch.coverage import (
    assembly_fer_study,
    largest_rectangle,
    measure_fer,
)
from hbis_torch.system.stitch.refine import fit_rotation, refine_homographies
from hbis_torch.system.stitch.stitch import (
    design_homographies,
    make_canvas,
    rebin_homographies,
    stitch,
    stitch_array,
    view_corners,
    view_outlines,
)

ARRAY = CameraArray()


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def scene():
    return default_scene(ARRAY)


def test_design_stitch_reproduces_the_scene_on_the_canvas(scene):
    """A perfect array stitched with K R K^-1 puts every view where the scene really is."""
    b = 8
    views = ArrayRenderer(ARRAY, scene).views(0.0, b)
    pano = stitch_array(views, ARRAY, b)
    c = pano.canvas
    yy, xx = torch.meshgrid(torch.arange(c.shape[0], dtype=torch.float64),
                            torch.arange(c.shape[1], dtype=torch.float64), indexing="ij")
    direct = scene.render(c.to_directions(torch.stack((xx, yy), -1))[..., :2] * 50.0, ARRAY.footprint_mm(b))
    covered = pano.coverage > 0
    error = (pano.image - direct).abs()[covered]
    assert float(error.mean()) < 0.02
    # A deliberately wrong layout (C23 swapped with C21) does not reproduce it.
    wrong = design_homographies(ARRAY, b)[[0, 1, 2, 5, 4, 3, 6, 7, 8]]
    bad = stitch(views, wrong, c)
    assert float((bad.image - direct).abs()[covered & (bad.coverage > 0)].mean()) > 3 * float(error.mean())


def test_refinement_recovers_a_misassembled_layout(scene):
    """Assembly errors of about a degree: SIFT + RANSAC find the true homographies."""
    b = 4
    array = ARRAY.with_assembly_errors(0.8, seed=5)
    renderer = ArrayRenderer(array, scene, periphery_sensor(SensorModel(), array.system.object_pixel_mm))
    views = renderer.views(0.0, b)
    predicted = design_homographies(array, b)
    truth = design_homographies(array, b, array.rotations)
    corners = view_corners(array.view_shape(b))

    def worst(h):
        return float((apply_homography(h, corners) - apply_homography(truth, corners))
                     .norm(dim=-1).max())

    result = refine_homographies(views, predicted, gate_px=np.radians(3.0) * float(array.intrinsics(b)[0, 0]),
                                 num_features=800, intrinsics=array.intrinsics(b))
    assert all(result.ok), result.messages
    assert worst(predicted) > 10.0  # the design alone is off by many pixels
    assert worst(result.homographies) < 1.0  # refined: under a pixel even at the far corners


def test_refinement_keeps_the_design_where_nothing_matches():
    views = torch.full((9, 60, 80), 0.5)
    predicted = design_homographies(ARRAY, 16)
    result = refine_homographies(views, predicted, num_features=100)
    assert not any(ok for name, ok in zip(CAMERA_NAMES, result.ok) if name != "C22")
    assert torch.equal(result.homographies, predicted.double())
    assert len(result.messages) == 8
    with pytest.raises(HbisInputError):
        refine_homographies(torch.full((8, 60, 80), 0.5), predicted)


def test_fit_rotation_is_exact_on_noise_free_correspondences():
    k = ARRAY.intrinsics(2)
    rot = ARRAY.with_assembly_errors(2.0, seed=3).rotations[5]
    src = torch.rand(40, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 400
    dst = apply_homography(k @ rot @ torch.linalg.inv(k), src)
    assert torch.allclose(fit_rotation(src, dst, k), rot, atol=1e-10)


def test_rebinned_homographies_match_the_other_binning():
    array = ARRAY.with_assembly_errors(1.0, seed=2)
    h2 = design_homographies(array, 2, array.rotations)
    h8 = design_homographies(array, 8, array.rotations)
    assert torch.allclose(rebin_homographies(h2, 2, 8), h8, atol=1e-9)


def test_fer_from_the_stitched_coverage_matches_the_design():
    b = 4
    h = design_homographies(ARRAY, b)
    canvas = make_canvas(ARRAY, h, b)
    pano = stitch(torch.zeros(9, *ARRAY.view_shape(b)), h, canvas)
    fer = measure_fer(pano.coverage, canvas, ARRAY.system.camera)
    theory = design(ARRAY.system, 15.0, 10.0)
    # through the axis: the design's 2 (varphi + theta), to a canvas pixel (0.09 deg at b = 4)
    assert fer["central"].fov_h_deg == pytest.approx(theory.fov_h_deg, abs=0.1)
    assert fer["central"].fov_v_deg == pytest.approx(theory.fov_v_deg, abs=0.1)
    assert fer["central"].fer_h == pytest.approx(theory.fer_h, abs=0.005)
    assert fer["rectangle"].fer_h <= fer["central"].fer_h + 1e-9
    assert fer["rectangle"].fer_v <= fer["central"].fer_v + 1e-9
    # Pull C23 inward by 3 degrees: the horizontal FOV shrinks by about 3 degrees.
    closer = CameraArray(ARRAY.system, 12.0, 10.0)
    h2 = design_homographies(closer, b)
    canvas2 = make_canvas(closer, h2, b)
    fer2 = measure_fer(stitch(torch.zeros(9, *ARRAY.view_shape(b)), h2, canvas2).coverage, canvas2,
                       ARRAY.system.camera)
    assert fer["central"].fov_h_deg - fer2["central"].fov_h_deg == pytest.approx(6.0, abs=0.2)


def test_assembly_errors_shrink_the_covered_rectangle():
    perfect = assembly_fer_study(ARRAY, 0.0, seeds=[0])
    theory = design(ARRAY.system, 15.0, 10.0)
    assert perfect["central_fer_h_mean"] == pytest.approx(theory.fer_h, abs=0.01)
    assert perfect["central_fer_v_mean"] == pytest.approx(theory.fer_v, abs=0.01)
    bent = assembly_fer_study(ARRAY, 1.5, seeds=range(4))
    assert bent["rectangle_fer_v_mean"] < perfect["rectangle_fer_v_mean"] - 0.05
    assert bent["rectangle_fer_h_min"] < perfect["rectangle_fer_h_mean"]


def test_largest_rectangle():
    mask = np.zeros((8, 10), dtype=bool)
    mask[1:6, 2:9] = True
    mask[3, 5] = False
    r0, r1, c0, c1 = largest_rectangle(mask)
    assert (r1 - r0 + 1) * (c1 - c0 + 1) == 15  # 5 x 3 beside the hole (better than 2 x 7 = 14)
    assert mask[r0:r1 + 1, c0:c1 + 1].all()


def test_stitch_rejects_bad_input():
    h = design_homographies(ARRAY, 16)
    canvas = make_canvas(ARRAY, h, 16)
    with pytest.raises(HbisInputError):
        stitch(torch.zeros(9, 60), h, canvas)
    with pytest.raises(HbisInputError):
        stitch(torch.full((9, 60, 80), float("nan")), h, canvas)
    with pytest.raises(HbisInputError):
        make_canvas(ARRAY, h, 16, scale=0.0)


def test_a_homography_that_sends_a_view_to_infinity_is_refused():
    h = design_homographies(ARRAY, 16)
    shape = ARRAY.view_shape(16)
    assert torch.equal(view_outlines(h, shape), apply_homography(h, view_corners(shape)))
    horizon = h.clone()
    corner = view_corners(shape)[2]  # the bottom-right corner goes to w = 0
    horizon[4, 2] = torch.tensor([-1.0 / float(corner[0]), 0.0, 1.0])
    with pytest.raises(HbisInputError, match="infinity"):
        view_outlines(horizon, shape)
    with pytest.raises(HbisInputError, match="infinity"):
        make_canvas(ARRAY, horizon, 16)
