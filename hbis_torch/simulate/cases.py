"""The benchmark's test stacks: which scenes, where on the sensor, simulated how.

benchmarks/bench_learned.py measures every super-resolution method's speed and error on these
stacks. (The learned method's held-out validation is training/eval_matrix.py.)
Case i of a ROI size is ``scene_cases(size)[i]``, placed at ``roi_for(system, size, i)`` and
simulated by ``make_stack(system, h, roi, scene, 1000 + i)``. The scenes are procedural
(:data:`SYNTHETIC_CASES`: the kind the network is trained on, with new seeds) and photographs
from scikit-image (:data:`PHOTO_CASES`: held out of every training pool).
"""

from __future__ import annotations

from hbis_torch.config import FoveaSystem
from hbis_torch.scan import plan_scan
from hbis_torch.simulate.catalog import SceneSpec, load_scene
from hbis_torch.simulate.rasters import HELD_OUT_PHOTOS
from hbis_torch.simulate.stacks import simulate_stack

SYNTHETIC_CASES = ("words", "texture")
PHOTO_CASES = HELD_OUT_PHOTOS[:3]  # camera, astronaut, coffee


def scene_cases(size) -> list[tuple[str, str]]:
    """(kind, scene) pairs measured at one ROI size (None: the full frame), in order; case i
    sits at ``roi_for(system, size, i)`` and is simulated with seed 1000 + i.

    Parameters
    ----------
    size : int or None
        Side of the square ROI, sensor pixels; None for the full frame.

    Returns
    -------
    list of (str, str)
        (``"synthetic"`` or ``"photo"``, scene name); fewer cases above 128 pixels, where every
        run takes long.
    """
    if size is None or size > 128:  # fewer scenes where every run takes long
        return [("synthetic", "words"), ("photo", "camera"), ("photo", "astronaut")][:2 if size is None else 3]
    return [("synthetic", s) for s in SYNTHETIC_CASES] + [("photo", p) for p in PHOTO_CASES]


def roi_for(system: FoveaSystem, size, index: int):
    """ROI of ``size`` (side or None for the full frame) at the centre, or near a corner.

    Parameters
    ----------
    system : FoveaSystem
        Its camera sets the sensor's size.
    size : int or None
        Side of the square ROI, sensor pixels; None for the full frame.
    index : int
        The case's index: cases 0, 3, ... sit at the centre, 1, 4, ... 16 pixels from the
        top-left corner, 2, 5, ... 16 pixels from the bottom-right one.

    Returns
    -------
    (int, int, int, int)
        (u0, v0, width, height), sensor pixels.
    """
    cam = system.camera
    if size is None:
        return (0, 0, cam.cols, cam.rows)
    spots = [((cam.cols - size) // 2, (cam.rows - size) // 2), (16, 16), (cam.cols - size - 16, cam.rows - size - 16)]
    u0, v0 = spots[index % len(spots)]
    return (u0, v0, size, size)


def make_stack(system: FoveaSystem, h: int, roi, scene_name: str, seed: int):
    """Simulate the stack of one case: the scene fitted to the ROI's view with a 25 % margin.

    Parameters
    ----------
    system : FoveaSystem
    h : int
        Resolution improvement factor of the scan (``plan_scan(system, h)``).
    roi : (int, int, int, int)
        (u0, v0, width, height), sensor pixels (:func:`roi_for`).
    scene_name : str
        A built-in scene or photograph (``load_scene``).
    seed : int
        Seed of the scene's layout and of the sensor noise (1000 + case index).

    Returns
    -------
    stack : Stack
        F = h^2 frames (height, width), 12-bit, with the default sensor.
    truth : ndarray, shape (h height, h width), float
        Ground truth in [0, 1].
    """
    spec = SceneSpec.around_roi(roi[2], roi[3], system.object_pixel_mm)
    scene = load_scene(scene_name, spec, seed=seed)
    return simulate_stack(scene, system, plan_scan(system, h), roi=roi, seed=seed)
