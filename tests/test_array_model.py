"""The 3 x 3 array model: orientations, views, scene, sensor and the fovea's scans."""

import math

import numpy as np
import pytest
import torch

from hbis_torch.system.array.cameras import CAMERA_NAMES, FOVEA, CameraArray
from hbis_torch.system.array.render import ArrayRenderer
from hbis_torch.system.array.scene import MovingObject, PlanarScene, TextureLayer, Trajectory, photo_object
from hbis_torch.system.array.sensor import periphery_sensor, simulate_fovea_scan
from hbis_torch.config import FoveaSystem
from hbis_torch.design import varphi_c_deg
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import pinhole_landing
from hbis_torch.simulate import SensorModel

ARRAY = CameraArray()


pytestmark = pytest.mark.usefixtures("one_thread")


def _axis_angles(rotation):
    z = rotation[:, 2]
    return (math.degrees(math.atan2(float(z[0]), float(z[2]))),
            math.degrees(math.atan2(float(z[1]), float(z[2]))),
            math.degrees(math.acos(float(z[2]))))


def test_axes_sit_at_the_design_angles():
    rot = dict(zip(CAMERA_NAMES, ARRAY.rotations))
    assert _axis_angles(rot["C23"])[:2] == pytest.approx((15.0, 0.0), abs=1e-12)
    assert _axis_angles(rot["C21"])[:2] == pytest.approx((-15.0, 0.0), abs=1e-12)
    assert _axis_angles(rot["C12"])[:2] == pytest.approx((0.0, -10.0), abs=1e-12)
    assert _axis_angles(rot["C32"])[:2] == pytest.approx((0.0, 10.0), abs=1e-12)
    for corner in ("C11", "C13", "C31", "C33"):
        assert _axis_angles(rot[corner])[2] == pytest.approx(varphi_c_deg(15.0, 10.0), abs=1e-9)
    assert torch.equal(rot[FOVEA], torch.eye(3, dtype=torch.float64))


def test_assembly_errors_move_the_side_cameras_only():
    bad = ARRAY.with_assembly_errors(0.7, seed=1)
    moved = [math.degrees(math.acos(min(1.0, float((a[:, 2] * b[:, 2]).sum()))))
             for a, b in zip(ARRAY.rotations, bad.rotations)]
    assert moved[CAMERA_NAMES.index(FOVEA)] == 0.0
    side = [m for n, m in zip(CAMERA_NAMES, moved) if n != FOVEA]
    assert all(0.0 < m < 4.0 for m in side)
    assert torch.equal(ARRAY.with_assembly_errors(0.7, seed=1).rotations, bad.rotations)
    with pytest.raises(HbisInputError):
        ARRAY.with_assembly_errors(float("nan"))


def test_view_points_of_the_parked_fovea_and_a_side_camera():
    system = ARRAY.system
    parked = ARRAY.view_points(FOVEA, 1)
    assert torch.allclose(parked, pinhole_landing(system), atol=1e-12)
    # C23's centre (between the four middle pixels) looks along its axis: x = v tan(15 deg).
    side = ARRAY.view_points("C23", 2)
    rows, cols = side.shape[:2]
    centre = side[rows // 2 - 1:rows // 2 + 1, cols // 2 - 1:cols // 2 + 1].reshape(-1, 2).mean(0)
    assert float(centre[0]) == pytest.approx(50.0 * math.tan(math.radians(15.0)), abs=0.02)
    assert abs(float(centre[1])) < 0.02
    with pytest.raises(HbisInputError):
        ARRAY.view_points("C44")
    with pytest.raises(HbisInputError):
        ARRAY.view_shape(0)


def test_binned_intrinsics_map_binned_pixels_to_their_rays():
    k = ARRAY.intrinsics(4)
    rays = ARRAY.camera_rays(4)
    pix = (rays / rays[..., 2:3]) @ k.T
    rows, cols = ARRAY.view_shape(4)
    v, u = torch.meshgrid(torch.arange(rows, dtype=torch.float64), torch.arange(cols, dtype=torch.float64),
                          indexing="ij")
    assert torch.allclose(pix[..., 0], u, atol=1e-9) and torch.allclose(pix[..., 1], v, atol=1e-9)


def _checker_scene(system=FoveaSystem()):
    y, x = np.mgrid[0:400, 0:600]
    image = (((x // 20) + (y // 20)) % 2).astype(np.float32) * 0.6 + 0.2
    return PlanarScene(TextureLayer(torch.from_numpy(image), (-45.0, -30.0), 0.15), [], system.object_distance_mm)


def test_trajectory_and_moving_object():
    path = Trajectory((0.0, 1.0, 2.0), ((0.0, 0.0), (2.0, 0.0), (2.0, 4.0)))
    assert path.position(-1.0).tolist() == [0.0, 0.0]
    assert path.position(0.5).tolist() == [1.0, 0.0]
    assert path.position(1.5).tolist() == [2.0, 2.0]
    assert path.position(9.0).tolist() == [2.0, 4.0]
    with pytest.raises(HbisInputError):
        Trajectory((0.0, 0.0), ((0.0, 0.0), (1.0, 1.0)))
    scene = _checker_scene()
    bright = TextureLayer(torch.ones(10, 10), (0.0, 0.0), 0.1)
    scene.objects.append(MovingObject(bright, path, "white square"))
    at = torch.tensor([[2.0, 2.0]], dtype=torch.float64)
    assert float(scene.render(at, 0.01, t_s=1.5)[0]) == pytest.approx(1.0)
    assert float(scene.render(at, 0.01, t_s=0.0)[0]) < 0.9
    with pytest.raises(HbisInputError):
        TextureLayer(torch.tensor([[float("nan"), 0.0], [0.0, 0.0]]), (0.0, 0.0), 0.1)
    with pytest.raises(HbisInputError):
        scene.render(torch.zeros(3), 0.1)


def test_scene_adapter_matches_the_scene():
    scene = _checker_scene()
    at = scene.at(0.0, (1.5, -2.0))
    pts = torch.rand(2000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 10 - 5
    direct = scene.render(pts, 0.01)
    local = at.sample(pts - torch.tensor([1.5, -2.0], dtype=torch.float64), 0.01, relative=True)
    # the simulator hands over float32 local coordinates: ~1e-6 mm, times the checker's slope
    assert float((direct - local).abs().max()) < 1e-4


def test_views_go_through_the_data_branch_sensor_with_binning():
    scene = PlanarScene(TextureLayer(torch.full((8, 8), 0.5), (-60.0, -60.0), 15.0), [], 50.0)
    sensor = SensorModel(full_well_e=1000.0, read_noise_e=5.0)
    renderer = ArrayRenderer(ARRAY, scene, periphery_sensor(sensor, ARRAY.system.object_pixel_mm))
    noise = [float(renderer.view("C22", 0.0, b, seed=3).std()) for b in (4, 8)]
    # Digital binning: b x b pixels summed, so the relative noise falls by the factor b.
    assert noise[0] / noise[1] == pytest.approx(2.0, rel=0.15)
    views = renderer.views(0.0, 8)
    assert views.shape == (9, 120, 160) and float(views.min()) >= 0 and float(views.max()) <= 1
    busy = renderer.views(0.0, 8, fovea_phases_deg=None)
    assert float(busy[CAMERA_NAMES.index(FOVEA)].abs().max()) == 0.0


def test_fovea_scan_frames_come_from_simulate_stack():
    system = ARRAY.system
    scene = _checker_scene(system)
    phases = torch.tensor([[5.0, 70.0], [5.1, 70.0], [5.0, 70.1], [5.1, 70.1]], dtype=torch.float64)
    roi = (600, 440, 32, 32)
    stack, truth = simulate_fovea_scan(scene, system, phases, 0, 2, roi, [0.0] * 4)
    assert stack.frames.shape == (4, 32, 32) and truth.shape == (64, 64)
    assert stack.reference_index == 0 and list(stack.roi) == list(roi)
    assert np.allclose(stack.phases_deg, phases.numpy())
    assert 0.15 < float(stack.to_float().mean()) < 0.85
    # An object moving during the scan: frames rendered per instant, no single truth.
    moving = PlanarScene(scene.background, [photo_object("page", 0.01, Trajectory((0.0, 1.0), ((0.0, 0.0), (5.0, 0.0))))], 50.0)
    stack2, truth2 = simulate_fovea_scan(moving, system, phases, 0, 2, roi, [0.0, 0.1, 0.2, 0.3])
    assert truth2 is None and stack2.frames.shape == (4, 32, 32)
    assert stack2.meta["frame_times_s"] == [0.0, 0.1, 0.2, 0.3]
