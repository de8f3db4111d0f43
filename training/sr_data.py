"""Training examples for the SR network: (registered frames, offsets, truth) patches.

STAND-IN: until the data helper's simulator lands, examples come from a small stand-in that
box-filters a random vector scene and samples it at nominal scan offsets with a random scale and
bias (what the optics do at the sensor's corners). Replaced by the real simulator before release.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage import draw

from hbis_torch.scan import scan_offsets
from hbis_torch.sr.learned import prepare_inputs


def random_scene(rng: np.random.Generator, size: int) -> np.ndarray:
    """A (size, size) float64 scene in [0, 1]: shapes, lines and a grating on a gradient."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    img = rng.uniform(0.1, 0.9) + rng.uniform(-0.3, 0.3) * (xx - 0.5) + rng.uniform(-0.3, 0.3) * (yy - 0.5)
    for _ in range(rng.integers(3, 12)):
        kind = rng.integers(0, 4)
        value = rng.uniform(0, 1)
        if kind == 0:
            rr, cc = draw.disk(rng.uniform(0, size, 2), rng.uniform(2, size / 3), shape=img.shape)
        elif kind == 1:
            pts = rng.uniform(0, size, (rng.integers(3, 6), 2))
            rr, cc = draw.polygon(pts[:, 0], pts[:, 1], shape=img.shape)
        elif kind == 2:
            r0, c0, r1, c1 = rng.integers(0, size, 4)
            rr, cc, _ = draw.line_aa(r0, c0, r1, c1)
            keep = (rr < size) & (cc < size)
            rr, cc = rr[keep], cc[keep]
        else:
            f = rng.uniform(0.01, 0.25)
            angle = rng.uniform(0, np.pi)
            grating = 0.5 + 0.5 * np.sin(2 * np.pi * f * (np.cos(angle) * xx + np.sin(angle) * yy) * size)
            mask = np.zeros(img.shape, bool)
            rr, cc = draw.disk(rng.uniform(0, size, 2), rng.uniform(size / 8, size / 3), shape=img.shape)
            img[rr, cc] = grating[rr, cc]
            continue
        img[rr, cc] = value
    return np.clip(img, 0, 1)


def standin_example(rng: np.random.Generator, h: int, patch: int):
    """One example: frames (h^2, P, P), positions (h^2, P, P, 2), truth (hP, hP)."""
    fine_per_hr = 2
    margin = 3
    n = patch + 2 * margin
    scale = h * fine_per_hr  # fine samples per LR pixel
    scene = random_scene(rng, n * scale)
    lr_box = ndimage.uniform_filter(scene, scale, mode="nearest")
    hr_box = ndimage.uniform_filter(scene, fine_per_hr, mode="nearest")
    offsets, _ = scan_offsets(h)
    gain = 1 + rng.uniform(0, 0.09)
    bias = rng.uniform(-0.06, 0.06, 2)
    shifts = offsets.numpy() / h * gain + bias  # (F, 2) LR pixels
    shifts[_] = 0.0  # the reference frame defines the grid
    yy, xx = np.mgrid[0:patch, 0:patch].astype(np.float64)
    grid = np.stack((xx, yy), -1)
    positions = grid[None] + shifts[:, None, None, :]
    frames = []
    noise = rng.uniform(0.001, 0.02)
    for k in range(h * h):
        # fine coordinate of LR position x: (x + margin + 0.5) * scale - 0.5
        fx = (positions[k, ..., 0] + margin + 0.5) * scale - 0.5
        fy = (positions[k, ..., 1] + margin + 0.5) * scale - 0.5
        f = ndimage.map_coordinates(lr_box, [fy, fx], order=1, mode="nearest")
        f = f + rng.normal(0, noise, f.shape)
        frames.append(np.round(np.clip(f, 0, 1) * 4095) / 4095)
    hr = np.arange(h * patch)
    hy, hx = np.meshgrid(hr, hr, indexing="ij")
    ty = ((hy + 0.5) / h - 0.5 + margin + 0.5) * scale - 0.5
    tx = ((hx + 0.5) / h - 0.5 + margin + 0.5) * scale - 0.5
    truth = ndimage.map_coordinates(hr_box, [ty, tx], order=1, mode="nearest")
    return np.stack(frames).astype(np.float32), positions, truth.astype(np.float32)


def make_batch(rng: np.random.Generator, h: int, patch: int, batch: int):
    """A batch: frames (B, h^2, P, P), offsets (B, 2h^2, P, P), truth (B, 1, hP, hP), float32."""
    frames, offsets, truths = [], [], []
    for _ in range(batch):
        f, pos, truth = standin_example(rng, h, patch)
        fr, off = prepare_inputs(f, pos, h)
        frames.append(fr)
        offsets.append(off)
        truths.append(truth[None])
    return np.stack(frames), np.stack(offsets), np.stack(truths)
