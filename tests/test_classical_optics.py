"""The classical method under lenses blurrier than the pixels: the scene prior is fitted only
where the lens passes the scene, so a quiet stack through a slow lens gives a finite image."""

import dataclasses

import numpy as np
import pytest

from hbis_torch.config import FoveaSystem
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct.classical import optics_cutoff, reconstruct_classical
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SceneSpec, SensorModel, load_scene, simulate_stack


@pytest.mark.parametrize("f_number", [11.0, 22.0])
@pytest.mark.parametrize("size", [20, 32])
def test_a_slow_lens_on_a_quiet_sensor_gives_a_finite_faithful_image(f_number, size):
    base = FoveaSystem()
    system = dataclasses.replace(base, camera=dataclasses.replace(base.camera, f_number=f_number))
    assert optics_cutoff(system) < 0.7  # the lens, not the pixels, limits the detail
    pixel = system.object_pixel_mm
    spec = SceneSpec(size_mm=(size * pixel * 1.25,) * 2, pixel_mm=pixel, detail_mm=pixel / 16)
    # 300,000 e-, 16 bit: the noise sits below the deblurring's floor (a 20 x 20 ROI at F 11 gave
    # NaN before the fit left out the rings beyond the cutoff)
    stack, truth = simulate_stack(load_scene("words", spec, seed=3), system, plan_scan(system, 2),
                                  roi=(600, 400, size, size), seed=3,
                                  sensor=SensorModel(full_well_e=300_000, read_noise_e=2.0, bit_depth=16))
    image = reconstruct_classical(stack, "optics")
    assert np.isfinite(image).all()
    assert psnr(np.asarray(truth)[4:-4, 4:-4], image[4:-4, 4:-4]) > 40
