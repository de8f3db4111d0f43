"""The peer **vidsr** (``pip install vidsr``, MIT) as a function: burst frames in, its SR image out.

Benchmark-only: the package never imports this, and nothing needs vidsr but the benchmarks that
name it (they skip its row where it is absent: :func:`available`).

vidsr's ``sr`` command reads a video; this runs the same steps of its ``cmd_sr`` on frames held in
memory, with its own functions, in its best setting for fidelity (its Richardson-Lucy, unsharp
mask and contrast steps are for viewing and cost PSNR):

* ECC registration through its stages up to a homography (``--motion homography``: translation
  on a pyramid, then translation, euclidean, affine, homography, each kept only if it fits
  better), each frame against the reference, started from its neighbour's warp and from phase
  correlation, as ``cmd_sr`` does (the whole frame is the region of interest);
* its frame rejection (normalised cross-correlation under 0.5, residual outliers beyond 3 MAD,
  duplicates) and per-frame weights (correlation x relative sharpness), as ``cmd_sr``;
* median fusion (``--fusion median``) of the frames warped bicubically onto the output grid;
* 12 iterations of its back-projection (``--ibp 12``, step 0.7) with its default PSF
  (sigma 0.35 S output px);
* no Richardson-Lucy (``--rl 0``), no unsharp mask (``--unsharp 0``), no CLAHE (``--clahe 0``).

The reference is frame 0 (``--ref 0``; vidsr would otherwise pick the sharpest), so that the
output lies on the same grid as the truth. vidsr processes three colour channels: colour frames
(F, H, W, 3) are registered on their grey (OpenCV's BT.601 conversion, as vidsr's own
``to_gray32``) and fused and back-projected channel by channel, and the three come back; grey
frames are handed to it as three equal channels (what it does with a grey video) and channel 0
comes back.
Frames go in as float32 in [0, 1] rather than through an 8-bit video, so vidsr sees the same
16-bit data as the project.
"""

from __future__ import annotations

import numpy as np

#: vidsr's defaults for what this does not change (its ``sr`` parser's).
HP_SIGMA, ECC_ITERS, ECC_EPS, MODEL_MARGIN = 3.0, 200, 1e-6, 0.0
MIN_NCC, REJECT_K, DUP_EPS, LAM = 0.5, 3.0, 1e-5, 0.7
#: The fidelity setting.
MOTION, FUSION, IBP = "homography", "median", 12


def available() -> bool:
    """Whether vidsr (and OpenCV, which it needs) imports."""
    try:
        import vidsr  # noqa: F401
    except Exception:  # vidsr exits or raises on a missing OpenCV or ffmpeg  # pragma: no cover
        return False
    return True


def version() -> str | None:
    """vidsr's version, or None where it is absent."""
    if not available():
        return None
    import vidsr

    return str(getattr(vidsr, "__version__", "unknown"))


def vidsr_sr(frames: np.ndarray, scale: int, reference: int = 0, ibp: int = IBP, verbose: bool = False) -> np.ndarray:
    """vidsr's super-resolved image of a burst, in its fidelity setting (module docstring).

    Parameters
    ----------
    frames : np.ndarray, shape (F, H, W) or (F, H, W, 3) (RGB)
        uint8, uint16 (all 16 bits) or float in [0, 1].
    scale : int
        S.
    reference : int
        The frame whose grid the output refines.
    ibp : int
        Back-projection iterations (12 in the fidelity setting).
    verbose : bool
        Let vidsr print its per-iteration lines.

    Returns
    -------
    np.ndarray, shape (S H, S W) (or (S H, S W, 3) for colour frames), float32 in [0, 1]
    """
    import cv2
    import vidsr as v

    frames = np.asarray(frames)
    if frames.dtype == np.uint8 or frames.dtype == np.uint16:
        images = [f.astype(np.float32) / float(np.iinfo(frames.dtype).max) for f in frames]
    else:
        images = [np.asarray(f, dtype=np.float32) for f in frames]
    colour = frames.ndim == 4
    grays = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in images] if colour else images
    n, (h, w) = len(grays), grays[0].shape
    roi = (0, 0, w, h)
    sharps = [v.sharpness(g) for g in grays]
    mask = v.build_mask((h, w), roi, 1.6)
    preps = [v.prep_for_align(g, HP_SIGMA) for g in grays]
    ref_prep, ref_gray = preps[reference], grays[reference]

    warps, rhos = {}, {}
    for i in sorted(range(n), key=lambda i: abs(i - reference)):  # outward from the reference
        if i == reference:
            warps[i], rhos[i] = np.eye(3, dtype=np.float32), 1.0
            continue
        prev = warps.get(i - 1 if i > reference else i + 1)
        W, rho = v.align_frame(ref_prep, preps[i], mask, MOTION, prev, ECC_ITERS, ECC_EPS, pyramid=True,
                               margin=MODEL_MARGIN)
        if W is None:
            W, rho = np.eye(3, dtype=np.float32), -1.0
        warps[i], rhos[i] = W, rho

    m = mask > 0
    residual, ncc = np.ones(n), np.zeros(n)
    for i in range(n):
        aligned = v.warp_to_ref(grays[i], warps[i], (w, h), cv2.INTER_LINEAR)
        sel = m & (v.warp_to_ref(np.ones_like(grays[i]), warps[i], (w, h), cv2.INTER_NEAREST) > 0.99)
        if sel.sum() > 32:
            residual[i] = float(np.mean(np.abs(aligned[sel] - ref_gray[sel])))
            ncc[i] = v.ncc(ref_prep, v.warp_to_ref(preps[i], warps[i], (w, h), cv2.INTER_LINEAR), sel)
    med = float(np.median(residual))
    mad = float(np.median(np.abs(residual - med))) * 1.4826 + 1e-6
    duplicate = [i > 0 and float(np.abs(grays[i] - grays[i - 1]).mean()) < DUP_EPS for i in range(n)]
    used = [i for i in range(n) if i == reference or not (duplicate[i] or ncc[i] < MIN_NCC
                                                          or residual[i] > med + REJECT_K * mad)]

    T = v.hr_transform(roi, float(scale))
    hr_size = (w * scale, h * scale)
    stack = np.empty((len(used), h * scale, w * scale, 3), np.float32)
    obs, wlist, weights = [], [], np.ones(len(used), np.float32)
    smed = float(np.median([sharps[i] for i in used])) or 1.0
    for k, i in enumerate(used):
        f3 = images[i] if colour else np.repeat(grays[i][..., None], 3, -1)
        hr = v.warp_lr_to_hr(f3, warps[i], T, hr_size, cv2.INTER_CUBIC)
        cov = v.warp_lr_to_hr(np.ones((h, w), np.float32), warps[i], T, hr_size, cv2.INTER_NEAREST)
        hr[cov < 0.99] = np.nan
        stack[k] = hr
        obs.append(f3)
        wlist.append(warps[i])
        weights[k] = max(0.05, ncc[i] if i != reference else 1.0) * min(1.0, sharps[i] / smed) ** 0.5
    weights /= weights.mean()
    fused, _ = v.fuse_stack(stack, weights, FUSION, 0.25)
    del stack
    psf = 0.35 * scale
    out = v.back_project(fused, obs, wlist, T, weights, ibp, psf, LAM, verbose=verbose) if ibp > 0 else fused
    return np.ascontiguousarray(out if colour else out[..., 0], dtype=np.float32)
