"""Two-stage foveation: detection, steering, the loop's stages, the composite and the volumes."""

import math

import numpy as np
import pytest
import torch

from hbis_torch.system.array.cameras import CameraArray
from hbis_torch.system.composite.composite import Inlay, composite
from hbis_torch.system.foveation.detect import motion_blobs
from hbis_torch.system.device import SimulatedHBIS
from hbis_torch.system.foveation.loop import LoopConfig, TwoStageLoop
from hbis_torch.system.array.render import ArrayRenderer
from hbis_torch.system.array.scenario import default_path, default_scene
from hbis_torch.system.array.scene import MovingObject, PlanarScene, TextureLayer, Trajectory
from hbis_torch.system.array.sensor import periphery_sensor, simulate_fovea_scan
from hbis_torch.errors import OutOfScanField
from hbis_torch.system.foveation.steering import (deviation_window_mm, in_scan_field,
                                       parked_phases_near, plan_fovea_scan, steer)
from hbis_torch.system.stitch.stitch import stitch_array
from hbis_torch.system.composite.volumes import bandwidth, foveal_ratio
from hbis_torch.design import bsr
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import exit_directions, land_on_plane, rays_at
from hbis_torch.simulate import SensorModel

ARRAY = CameraArray()
SYSTEM = ARRAY.system


pytestmark = pytest.mark.usefixtures("one_thread")


def test_motion_blobs_find_a_moved_square():
    a = torch.full((60, 80), 0.3)
    b = a.clone()
    a[10:16, 20:26] = 0.9
    b[12:18, 24:30] = 0.9
    blobs = motion_blobs(a, b, threshold=0.1)
    assert len(blobs) == 1
    u, v = blobs[0].centre_px
    assert 20 < u < 30 and 10 < v < 18  # between where it was and where it is
    assert motion_blobs(a, a.clone()) == []
    with pytest.raises(HbisInputError):
        motion_blobs(a, b[:-1])
    with pytest.raises(HbisInputError):
        motion_blobs(a, torch.full_like(a, float("nan")))


@pytest.mark.parametrize("target", [(3.0, 2.0), (0.0, 0.0), (-9.0, 4.0), (12.0, -1.0), (2.0, 9.0)])
def test_the_steered_fovea_lands_on_the_object(target):
    pointing = steer(SYSTEM, target, 128, near_deg=(0.0, 180.0))
    u, v = pointing.object_px
    ray = rays_at(SYSTEM.camera, torch.tensor(u, dtype=torch.float64), torch.tensor(v, dtype=torch.float64))
    landed = land_on_plane(exit_directions(ray, *pointing.phases_deg, SYSTEM.prisms), SYSTEM.object_distance_mm)
    assert float((landed - torch.tensor(target, dtype=torch.float64)).norm()) < 1e-9
    u0, v0, w, h = pointing.roi
    assert abs(u0 + (w - 1) / 2 - u) <= 0.5 and abs(v0 + (h - 1) / 2 - v) <= 0.5
    assert pointing.residual_mm < 1e-9
    # The phase difference stays inside the window the scan needs.
    delta = abs((pointing.phases_deg[0] - pointing.phases_deg[1] + 180.0) % 360.0 - 180.0)
    assert 30.0 - 1e-6 <= delta <= 150.0 + 1e-6
    # The coarse (paraxial) answer is close: the exact solver only corrects it.
    assert max(abs(a - b) for a, b in zip(pointing.coarse_phases_deg, pointing.phases_deg)) < 2.0


def test_the_steered_fovea_sees_the_object_in_the_middle_of_its_roi():
    """Rendered: a bright square on a dark plane is imaged at the ROI's centre."""
    target = (4.0, -3.0)
    square = TextureLayer(torch.ones(8, 8), (0.0, 0.0), 0.05)
    dark = TextureLayer(torch.full((4, 4), 0.1), (-40.0, -40.0), 20.0)
    scene = PlanarScene(dark, [MovingObject(square, Trajectory((0.0,), (target,)))], SYSTEM.object_distance_mm)
    pointing = steer(SYSTEM, target, 64)
    plan = plan_fovea_scan(SYSTEM, 2, pointing)
    stack, _ = simulate_fovea_scan(scene, SYSTEM, plan.phases_deg, plan.reference_index, 2, pointing.roi,
                                   [0.0] * len(plan.phases_deg), SensorModel(noise=False))
    frame = stack.to_float()[plan.reference_index] - 0.1
    frame = frame.clamp(min=0)
    v, u = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
    centroid = (float((frame * u).sum() / frame.sum()), float((frame * v).sum() / frame.sum()))
    assert centroid == pytest.approx((31.5, 31.5), abs=0.6)


def test_scan_field_limits():
    r_min, r_max = deviation_window_mm(SYSTEM)
    assert 0 < r_min < r_max < SYSTEM.object_distance_mm * math.tan(math.radians(4.01))
    assert in_scan_field(SYSTEM, (0.0, 0.0), 128)
    far = (30.0, 0.0)
    assert not in_scan_field(SYSTEM, far, 128)
    with pytest.raises(OutOfScanField):
        steer(SYSTEM, far, 128)
    # A bigger ROI has a smaller scan field.
    edge = (12.0, 0.0)
    assert in_scan_field(SYSTEM, edge, 64) and not in_scan_field(SYSTEM, edge, 600)
    with pytest.raises(HbisInputError):
        steer(SYSTEM, (float("nan"), 0.0))
    p1, p2 = parked_phases_near((10.0, 80.0))
    assert abs(abs(p1 - p2) - 180.0) < 1e-12 and max(abs(p1 - 10.0), abs(p2 - 80.0)) == pytest.approx(55.0)


def _fast_reconstruct(capture):
    """A stand-in for the SR step (the loop takes any reconstruct_fn): bicubic enlargement."""
    stack = capture.stack
    ref = stack.to_float()[stack.reference_index]
    return torch.nn.functional.interpolate(ref[None, None], scale_factor=stack.h, mode="bicubic")[0, 0].clamp(0, 1).numpy()


@pytest.fixture(scope="module")
def loop_run():
    path = default_path(stop_mm=(3.0, 2.0), speed_mm_s=12.0, start_x_mm=-15.0, end_x_mm=18.0, stop_s=1.0)
    scene = default_scene(ARRAY, path=path)
    renderer = ArrayRenderer(ARRAY, scene, periphery_sensor(SensorModel(), SYSTEM.object_pixel_mm))
    device = SimulatedHBIS(renderer, 8)
    config = LoopConfig(h=2, roi_size=96, duration_s=4.6)
    result = TwoStageLoop(device, config, _fast_reconstruct).run()
    return scene, config, result


def test_the_loop_goes_through_both_stages(loop_run):
    scene, config, result = loop_run
    kinds = result.kinds()
    for kind in ("start", "detected", "stage_two", "pointed", "scan_started", "scan_finished",
                 "super_resolved", "object_left", "stage_one", "end"):
        assert kind in kinds, kind
    assert kinds.index("stage_two") < kinds.index("super_resolved") < kinds.index("object_left")
    times = [e.t_s for e in result.events]
    assert times == sorted(times)
    kept = [c for c in result.captures if c.sr is not None]
    assert kept and kept[-1].sr.shape == (2 * 96, 2 * 96)
    # The kept scan saw the object at rest, inside the ROI.
    capture = kept[-1]
    obj = scene.object_position(capture.t_start_s)
    assert np.allclose(obj, scene.object_position(capture.t_end_s))
    assert np.linalg.norm(obj - np.asarray(capture.pointing.object_mm)) < 0.25


def test_the_loop_leaves_stage_two_when_the_object_leaves_the_scan_field(loop_run):
    scene, config, result = loop_run
    left = next(e for e in result.events if e.kind == "object_left")
    true_position = scene.object_position(left.t_s)
    assert not in_scan_field(SYSTEM, true_position, config.roi_size)
    # just before, the tracked object was still inside
    last_pointing = [e for e in result.events if e.kind == "pointed" and e.t_s <= left.t_s][-1]
    assert in_scan_field(SYSTEM, last_pointing.data["object_mm"], config.roi_size)
    after = result.events[result.events.index(left):]
    back = next(e for e in after if e.kind == "stage_one")
    assert back.stage == 1
    parking = next(e for e in after if e.kind == "prisms_moved")
    phi1, phi2 = parking.data["phases_deg"]
    assert abs(abs((phi1 - phi2 + 180.0) % 360.0 - 180.0) - 180.0) < 1e-9  # parked: opposed prisms
    assert all(e.stage == 1 for e in result.events[result.events.index(back):])


def test_composite_puts_the_inlay_where_the_scene_is():
    """Inlaying the ground truth: the composite there equals the scene rendered directly."""
    scene = default_scene(ARRAY)
    target = (3.0, 2.0)
    pointing = steer(SYSTEM, target, 64)
    plan = plan_fovea_scan(SYSTEM, 2, pointing)
    t = 4.0  # the default object stands still at (3, 2) mm
    stack, truth = simulate_fovea_scan(scene, SYSTEM, plan.phases_deg, plan.reference_index, 2, pointing.roi,
                                       [t] * len(plan.phases_deg), SensorModel(noise=False))
    b = 8
    pano = stitch_array(ArrayRenderer(ARRAY, scene).views(t, b), ARRAY, b)
    inlay = Inlay(truth, pointing.roi, 2, pointing.phases_deg, SYSTEM)
    zoom = 2 * b  # one composite pixel per truth pixel
    x, y = pano.canvas.from_directions(torch.tensor([target[0] / 50.0, target[1] / 50.0, 1.0],
                                                    dtype=torch.float64)).tolist()
    window = (round(x * zoom) - 40, round(y * zoom) - 40, 80, 80)
    out = composite(pano.image, pano.canvas, inlay, b, zoom=zoom, window=window, feather_hr_px=0)
    ys = (torch.arange(window[1], window[1] + 80, dtype=torch.float64) + 0.5) / zoom - 0.5
    xs = (torch.arange(window[0], window[0] + 80, dtype=torch.float64) + 0.5) / zoom - 0.5
    cy, cx = torch.meshgrid(ys, xs, indexing="ij")
    plane = pano.canvas.to_directions(torch.stack((cx, cy), -1))[..., :2] * 50.0
    direct = scene.render(plane, SYSTEM.object_pixel_mm / 2, t)
    # the truth is blurred by the lens and the pitch-p/2 pixel: compare after a matching blur
    blur = torch.nn.functional.avg_pool2d(direct[None, None], 3, 1, 1, count_include_pad=False)[0, 0]
    inner = (slice(10, 70), slice(10, 70))
    assert float(np.corrcoef(out[inner].flatten(), blur[inner].flatten())[0, 1]) > 0.95
    shifted = torch.roll(blur, 4, dims=1)
    assert np.corrcoef(out[inner].flatten(), shifted[inner].flatten())[0, 1] < 0.9
    with pytest.raises(HbisInputError):
        Inlay(truth[:-1], pointing.roi, 2, pointing.phases_deg, SYSTEM)


def test_foveal_ratio_and_bandwidth():
    pointing = steer(SYSTEM, (3.0, 2.0), 128)
    for h in (2, 4, 7):
        assert foveal_ratio(SYSTEM, pointing.roi, h, pointing.phases_deg) == pytest.approx(h, rel=0.02)
    frame = SYSTEM.camera.rows * SYSTEM.camera.cols
    fer_h, fer_v = 2.33, 2.17
    volumes = bandwidth(SYSTEM, 4, fer_h * fer_v * frame, pointing.roi, fer_h, fer_v)
    # With the whole FOV exactly FER_h FER_v frames, eq. 10's accounting is eq. 10.
    assert volumes["bsr_from_coverage"] == pytest.approx(bsr(4, fer_h, fer_v), abs=1e-12)
    assert volumes["bsr_demo_traffic"] > volumes["bsr_from_coverage"]  # a ROI scan sends less


@pytest.mark.parametrize("h", [0, 2.0, 17, True])
def test_loop_config_takes_h_by_the_one_rule(h):
    with pytest.raises(HbisInputError, match="h must be an integer from 1 to 16"):
        LoopConfig(h=h)
