"""The whole HBIS chain on built-in defaults (what ``hbis demo`` runs).

1. An array with assembly errors like the prototype's 3D-printed frame (the side cameras off by
   ``assembly_sigma_deg``), looking at the photo-wall scenario (:mod:`.scenario`).
2. Calibration: the nine views at time 0 (``panorama_binning``), homographies refined from the
   images (SIFT + RANSAC, :mod:`.refine`) against the design's K R K^-1.
3. The two-stage loop (:mod:`.loop`) on detection frames (``detection_binning``), super-resolving
   with ``reconstruct(stack, method)``.
4. At the time of the kept scan: the panorama (design and refined homographies), FER from its
   coverage (and over random assemblies, :func:`.coverage.assembly_fer_study`), the foveated
   composite, the foveal ratio and the BSR from the data volumes.
5. Images and figures into ``out_dir``; a summary dict (numbers, relative paths, event log).

Views are binned (stated in the summary): the panorama's pixels are ``panorama_binning`` sensor
pixels a side, the detection frames ``detection_binning``; the fovea's scans are full resolution.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.design import design
from hbis_torch.errors import HbisInputError
from hbis_torch.metrics import psnr
from hbis_torch.simulate import SensorModel
from hbis_torch.system.array.cameras import CAMERA_NAMES, CameraArray
from hbis_torch.system.device import SimulatedHBIS
from hbis_torch.system.array.render import ArrayRenderer
from hbis_torch.system.array.scenario import default_scene
from hbis_torch.system.array.scene import Trajectory
from hbis_torch.system.array.sensor import periphery_sensor
from hbis_torch.system.composite.composite import Inlay, composite, inlay_outline
from hbis_torch.system.composite.volumes import (
    bandwidth,
    covered_native_pixels,
    foveal_ratio,
)
from hbis_torch.system.foveation.loop import FoveaCapture, LoopConfig, TwoStageLoop
from hbis_torch.system.report.plots import (
    plot_panorama,
    plot_sr_pairs,
    plot_timeline,
    plot_views,
    save_png,
)
from hbis_torch.system.stitch.coverage import assembly_fer_study, measure_fer
from hbis_torch.system.stitch.refine import refine_homographies
from hbis_torch.system.stitch.stitch import (
    design_homographies,
    rebin_homographies,
    stitch_array,
    view_outlines,
)

#: The prototype's measured FER (paper section 4.2), for comparison.
PAPER_MEASURED_FER = {"h": 2.2, "v": 2.0}


@dataclass
class ChainConfig:
    """Settings of :func:`run_chain` (defaults: the demo's)."""

    h: int = 4
    roi_size: int = 160
    varphi_h_deg: float = 15.0
    varphi_v_deg: float = 10.0
    assembly_sigma_deg: float = 0.7
    seed: int = 3
    panorama_binning: int = 2
    detection_binning: int = 8
    duration_s: float = 9.0
    refine: bool = True
    method: str = "classical"
    model: str | None = None
    path: Trajectory | None = None  # the moving object's path (None: scenario.default_path())


#: The stages :func:`run_chain` times (``timings_s``) and shows in its progress bar.
STAGES = ("render views", "refine stitching", "two-stage loop", "panorama", "composite and measures",
          "SR quality", "pictures")


def make_reconstruct_fn(method: str, model: str | None = None):
    """``reconstruct_fn`` for the loop: ``hbis_torch.reconstruct.reconstruct(stack, method, ...)``."""
    from hbis_torch.reconstruct import reconstruct

    kwargs = {} if model is None else {"model": model}

    def run(capture: FoveaCapture) -> np.ndarray:
        return reconstruct(capture.stack, method=method, **kwargs)

    return run


def _stitching(array: CameraArray, renderer: ArrayRenderer, cfg: ChainConfig, log, lap) -> tuple:
    """The stitching homographies at the panorama's binning (refined from the first views unless
    switched off), the design ones, and what the refinement did (with its worst corner errors
    against the true assembly, in sensor pixels)."""
    b = cfg.panorama_binning
    design_h = design_homographies(array, b)
    log(f"[system] rendering the nine views ({array.view_shape(b)[1]} x {array.view_shape(b)[0]}, binned {b})")
    views0 = renderer.views(0.0, b, seed=1)
    lap("render views")
    if cfg.refine:
        focal = float(array.intrinsics(b)[0, 0])
        refined = refine_homographies(views0, design_h, gate_px=np.radians(2.5) * focal,
                                      intrinsics=array.intrinsics(b), seed=cfg.seed)
        homographies = refined.homographies
        refine_info = {"inliers": dict(zip(CAMERA_NAMES, refined.inliers)),
                       "refined": dict(zip(CAMERA_NAMES, refined.ok)), "messages": refined.messages}
    else:
        homographies, refine_info = design_h, {"messages": ["refinement switched off"]}
    true_h = design_homographies(array, b, array.rotations)

    def corner_error(hs):  # worst view-corner misplacement against the true assembly, native px
        shape = array.view_shape(b)
        return float((view_outlines(hs, shape) - view_outlines(true_h, shape)).norm(dim=-1).max()) * b

    refine_info["design_error_px"] = corner_error(design_h)
    refine_info["refined_error_px"] = corner_error(homographies)
    lap("refine stitching")
    return homographies, design_h, refine_info


def _composites(pano, inlay: Inlay, b: int, h: int) -> tuple:
    """The whole foveated composite, a zoomed window around the inlay, and the inlay's outline."""
    full = composite(pano.image, pano.canvas, inlay, b, zoom=1.0)
    outline = inlay_outline(pano.canvas, inlay)
    zoom = h * b / float(pano.canvas.A[0, 0])
    lo, hi = outline.amin(0) * zoom, outline.amax(0) * zoom
    pad = 0.45 * (hi - lo)
    x0, y0 = (lo - pad).floor().int().tolist()
    x1, y1 = (hi + pad).ceil().int().tolist()
    zoomed = composite(pano.image, pano.canvas, inlay, b, zoom=zoom, window=(x0, y0, x1 - x0, y1 - y0))
    return full, zoomed, outline


def _pictures(out: Path, cfg: ChainConfig, views, pano, pano_design, fer: dict, composites: tuple,
              capture: FoveaCapture, sub_image: np.ndarray, t_sr: float, timeline) -> dict:
    """Write every picture of the run into ``out``; returns their paths by name."""
    b = cfg.panorama_binning
    full, zoomed, outline = composites
    return {
        "views": plot_views(views, out / "views.png", f"the nine views at t = {t_sr:.2f} s (binned {b})"),
        "panorama": save_png(pano.image, out / "panorama.png"),
        "panorama_figure": plot_panorama(
            pano.image, pano.outlines, out / "fig8a_panorama.png",
            f"stitched panorama (refined homographies): FER_h = {fer['rectangle'].fer_h:.2f}, "
            f"FER_v = {fer['rectangle'].fer_v:.2f}",
            rectangle=fer["rectangle"].extent_px, inlay_outline=outline.numpy()),
        "panorama_design": plot_panorama(
            pano_design.image, pano_design.outlines, out / "panorama_design_angles.png",
            "the same views stitched with the design angles only (assembly errors show as seams)"),
        "composite": save_png(full, out / "foveated_composite.png"),
        "composite_zoom": save_png(zoomed, out / "foveated_composite_zoom.png"),
        "sr_fovea": save_png(capture.sr, out / "sr_fovea.png"),
        "sub_image": save_png(sub_image, out / "sub_image.png"),
        "sr_pairs": plot_sr_pairs(capture.sr, sub_image, cfg.h, out / "fig9_sr_vs_sub_image.png",
                                  f"super-resolved fovea (h = {cfg.h}, {cfg.method}) beside a sub-image",
                                  truth=capture.truth),
        "timeline": plot_timeline(timeline[0], out / "timeline.png", timeline[1]),
    }


def run_chain(out_dir, system: FoveaSystem = FoveaSystem(), config: ChainConfig = ChainConfig(), log=print) -> dict:
    """Run the chain, write its pictures into ``out_dir``; returns the summary (see module)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    from hbis_torch.progress import progress

    timings: dict[str, float] = {}
    clock = time.perf_counter()
    bar = progress(total=len(STAGES), desc="demo", unit="stage")

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = round(now - clock, 2)
        clock = now
        bar.set_postfix_str(name)
        bar.update()

    cfg = config
    nominal = CameraArray(system, cfg.varphi_h_deg, cfg.varphi_v_deg)
    array = nominal.with_assembly_errors(cfg.assembly_sigma_deg, cfg.seed)
    scene = default_scene(nominal, h=cfg.h, path=cfg.path)
    renderer = ArrayRenderer(array, scene, periphery_sensor(SensorModel(), system.object_pixel_mm))
    b = cfg.panorama_binning
    homographies, design_h, refine_info = _stitching(array, renderer, cfg, log, lap)
    log(f"[system] stitching error against the true assembly: design {refine_info['design_error_px']:.1f} px, "
        f"refined {refine_info['refined_error_px']:.2f} px (sensor pixels, worst view corner)")

    device = SimulatedHBIS(renderer, cfg.detection_binning,
                           calibration=rebin_homographies(homographies, b, cfg.detection_binning))
    loop_cfg = LoopConfig(h=cfg.h, roi_size=cfg.roi_size, duration_s=cfg.duration_s)
    log(f"[system] two-stage loop: {cfg.duration_s:g} s of simulated time, SR method {cfg.method!r}")
    result = TwoStageLoop(device, loop_cfg, make_reconstruct_fn(cfg.method, cfg.model)).run()
    lap("two-stage loop")
    kept = [c for c in result.captures if c.sr is not None]
    if not kept:
        raise HbisInputError("the loop made no super-resolved fovea (the object never held still in the scan field)")
    capture = kept[-1]
    t_sr = capture.t_start_s

    views = renderer.views(t_sr, b, seed=2)
    pano = stitch_array(views, array, b, homographies)
    pano_design = stitch_array(views, array, b, design_h)
    fer = measure_fer(pano.coverage, pano.canvas, system.camera)
    fer_design = measure_fer(pano_design.coverage, pano_design.canvas, system.camera)
    theory = design(system, cfg.varphi_h_deg, cfg.varphi_v_deg, h=cfg.h)
    study = [assembly_fer_study(nominal, sigma) for sigma in sorted({0.0, cfg.assembly_sigma_deg, 1.5})]
    lap("panorama")

    stack = capture.stack
    ref_phases = tuple(float(p) for p in stack.phases_deg[stack.reference_index])
    composites = _composites(pano, Inlay(capture.sr, tuple(stack.roi), cfg.h, ref_phases, system), b, cfg.h)
    ratio = foveal_ratio(system, stack.roi, cfg.h, ref_phases)
    area = covered_native_pixels(pano.coverage, pano.canvas, b)
    volumes = bandwidth(system, cfg.h, area, stack.roi, fer["rectangle"].fer_h, fer["rectangle"].fer_v,
                        design_fer=(theory.fer_h, theory.fer_v))
    lap("composite and measures")

    frames = stack.to_float().numpy()
    sub_image = frames[stack.reference_index]
    bicubic = torch.nn.functional.interpolate(torch.from_numpy(sub_image)[None, None], scale_factor=cfg.h,
                                              mode="bicubic", align_corners=False)[0, 0].clamp(0, 1).numpy()
    quality = {}
    if capture.truth is not None:
        quality = {"psnr_sr_db": psnr(capture.sr, capture.truth), "psnr_bicubic_db": psnr(bicubic, capture.truth)}
        # The classical method on the same stack, so that the report compares the two methods.
        classical = (capture.sr if cfg.method == "classical"
                     else make_reconstruct_fn("classical")(capture))
        quality["psnr_classical_db"] = psnr(classical, capture.truth)
    lap("SR quality")
    images = _pictures(out, cfg, views, pano, pano_design, fer, composites, capture, sub_image, t_sr,
                       (result.events, _truth_x(scene, result.end_s)))
    lap("pictures")
    bar.close()
    events = [e.to_dict() for e in result.events]
    return {
        "config": asdict(cfg),
        "binning": {"panorama": b, "detection": cfg.detection_binning, "fovea": 1},
        "refinement": refine_info,
        "fer": {
            "measured_refined": {k: v.to_dict() for k, v in fer.items()},
            "measured_design_stitch": {k: v.to_dict() for k, v in fer_design.items()},
            "theory": {"fer_h": theory.fer_h, "fer_v": theory.fer_v, "fov_h_deg": theory.fov_h_deg,
                       "fov_v_deg": theory.fov_v_deg},
            "paper_prototype_measured": PAPER_MEASURED_FER,
            "assembly_study": study,
        },
        "foveal_ratio": {"measured": ratio, "theory": cfg.h},
        "bandwidth": volumes,
        "sr": {"t_s": t_sr, "roi": list(stack.roi), "reference_phases_deg": list(ref_phases),
               "shape": list(capture.sr.shape), "method": cfg.method, "plan": capture.plan_source,
               **quality},
        "loop": {"captures": len(result.captures), "kept": len(kept), "end_s": result.end_s,
                 "kinds": sorted(set(result.kinds()))},
        "events": events,
        "images": {k: str(Path(v).relative_to(out)) for k, v in images.items()},
        "timings_s": timings,
    }


def _truth_x(scene, end_s: float, step_s: float = 0.02):
    times = np.arange(0.0, end_s + step_s, step_s)
    return times, np.array([scene.object_position(t)[0] for t in times])
