"""Physics-generated synthetic stacks: scenes, the fovea's forward model, sensor noise.

Main entry points::

    from hbis_torch.simulate import simulate_stack, SensorModel, load_scene, SceneSpec
    stack, truth = simulate_stack(scene, system, plan_scan(system, 4), roi=(512, 352, 256, 256))

docs/data.md describes the model and the output-grid convention. The network's training data
(pools of simulated stacks cut into crops) is hbis_torch.training.data; the
benchmark's test stacks are :mod:`hbis_torch.simulate.cases`.
"""

from hbis_torch.optics import landing_on_grid, sample_positions  # public here too, for the simulator's users
from hbis_torch.simulate.catalog import (
    BUILTIN_SCENES,
    PROCEDURAL,
    SceneSpec,
    load_scene,
)
from hbis_torch.simulate.forward import RenderedScan, render_scan
from hbis_torch.simulate.psf import airy_otf, airy_psf, blur_transfer, lens_otf
from hbis_torch.simulate.rasters import PHOTOS
from hbis_torch.simulate.scenes import (
    BarTarget,
    EdgesScene,
    FlatScene,
    GradientScene,
    GratingScene,
    ImageScene,
    Scene,
    SiemensStar,
)
from hbis_torch.simulate.sensor import SensorModel, expose
from hbis_torch.simulate.stacks import scene_for_roi, simulate_stack

__all__ = [
    "BUILTIN_SCENES",
    "PHOTOS",
    "PROCEDURAL",
    "BarTarget",
    "EdgesScene",
    "FlatScene",
    "GradientScene",
    "GratingScene",
    "ImageScene",
    "RenderedScan",
    "Scene",
    "SceneSpec",
    "SensorModel",
    "SiemensStar",
    "airy_otf",
    "airy_psf",
    "blur_transfer",
    "expose",
    "landing_on_grid",
    "lens_otf",
    "load_scene",
    "render_scan",
    "sample_positions",
    "scene_for_roi",
    "simulate_stack",
]
