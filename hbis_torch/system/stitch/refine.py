"""Refining the stitching homographies from the images, for an imperfect assembly.

Each side view is matched against the fovea's (parked) view, which overlaps all eight (the
corner views also against their two edge neighbours, with which they overlap more). Features
are Kornia's SIFT (hand-crafted: no downloaded weights), matched by mutual nearest neighbours
with Lowe's ratio test (``match_smnn``), pre-filtered by the design prediction (a match must
land within ``gate_px`` of where the design homography puts it: assembly errors are small), and
fitted by Kornia's RANSAC homography; through its inliers the final model is either that
homography (least squares) or, for cameras that share a centre, a rotation. A refined homography is kept only when enough inliers
support it; otherwise the design homography stays and a message says why.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import kornia.feature as KF
import torch
from kornia.geometry.homography import find_homography_dlt
from kornia.geometry.ransac import RANSAC
from torch import Tensor

from hbis_torch.errors import HbisInputError
from hbis_torch.registration.homography import apply_homography
from hbis_torch.system.array.cameras import CAMERA_NAMES, FOVEA_INDEX


@dataclass
class Refinement:
    """Result of :func:`refine_homographies`.

    Attributes
    ----------
    homographies : Tensor (V, 3, 3) float64, view pixel -> fovea pixel
    inliers : list of int, RANSAC inliers per view (the fovea: 0)
    ok : list of bool, whether the view's homography was refined
    messages : list of str
    """

    homographies: Tensor
    inliers: list = field(default_factory=list)
    ok: list = field(default_factory=list)
    messages: list = field(default_factory=list)


def _features(image: Tensor, detector: KF.SIFTFeature) -> tuple[Tensor, Tensor]:
    """Keypoint centres (N, 2) float64 (x, y) and descriptors (N, 128) of one (H, W) image."""
    with torch.no_grad():
        lafs, _, desc = detector(image[None, None].float())
    return KF.get_laf_center(lafs)[0].double(), desc[0]


def _inside(points: Tensor, shape: tuple[int, int], margin: float) -> Tensor:
    rows, cols = shape
    return ((points[:, 0] >= -margin) & (points[:, 0] <= cols - 1 + margin)
            & (points[:, 1] >= -margin) & (points[:, 1] <= rows - 1 + margin))


def fit_rotation(src: Tensor, dst: Tensor, intrinsics: Tensor) -> Tensor:
    """The rotation R (3, 3) float64 that best maps the rays of pixels ``src`` (N, 2) onto those
    of ``dst`` (N, 2) (both cameras with intrinsics K): least squares on the unit sphere, solved
    in closed form by SVD (orthogonal Procrustes / Kabsch)."""
    k_inv = torch.linalg.inv(intrinsics.double())

    def rays(p: Tensor) -> Tensor:
        r = torch.cat((p.double(), torch.ones_like(p[:, :1]).double()), 1) @ k_inv.T
        return r / r.norm(dim=-1, keepdim=True)

    a, b = rays(src), rays(dst)
    u, _, vh = torch.linalg.svd(b.T @ a)
    d = torch.sign(torch.linalg.det(u @ vh))
    return u @ torch.diag(torch.tensor([1.0, 1.0, float(d)], dtype=torch.float64)) @ vh


def _rotation_homography(src: Tensor, dst: Tensor, inliers: Tensor, intrinsics: Tensor,
                         inlier_px: float, rounds: int = 3) -> Tensor:
    """K R K^-1 through RANSAC's inliers, then re-fitted on the matches the rotation itself
    explains (RANSAC's 8-parameter model accepts some a rotation cannot)."""
    k_inv = torch.linalg.inv(intrinsics.double())
    keep = inliers
    for _ in range(rounds):
        h = intrinsics.double() @ fit_rotation(src[keep], dst[keep], intrinsics) @ k_inv
        residual = (apply_homography(h, src) - dst).norm(dim=-1)
        new_keep = residual <= inlier_px
        if int(new_keep.sum()) < 4 or torch.equal(new_keep, keep):
            break
        keep = new_keep
    return h


#: Side cameras matched first (each against the fovea), then the corners, each against the
#: fovea and its two refined neighbours (the corners' overlap with the fovea alone is small).
EDGES = ("C12", "C21", "C23", "C32")
CORNER_NEIGHBOURS = {"C11": ("C12", "C21"), "C13": ("C12", "C23"), "C31": ("C21", "C32"),
                     "C33": ("C23", "C32")}


def _pair_matches(a: tuple, b: tuple, h_ab: Tensor, shape, gate_px: float, ransac: RANSAC,
                  min_inliers: int):
    """RANSAC-consistent matches (src in view a, dst in view b) given the predicted H a -> b,
    or a sentence saying why there are none."""
    xy_a, desc_a = a
    xy_b, desc_b = b
    keep_a = _inside(apply_homography(h_ab, xy_a), shape, gate_px)
    keep_b = _inside(apply_homography(torch.linalg.inv(h_ab), xy_b), shape, gate_px)
    if int(keep_a.sum()) < min_inliers or int(keep_b.sum()) < min_inliers:
        return None, "too few features in the predicted overlap"
    _, idx = KF.match_smnn(desc_a[keep_a], desc_b[keep_b], th=0.95)
    src, dst = xy_a[keep_a][idx[:, 0]], xy_b[keep_b][idx[:, 1]]
    near = (apply_homography(h_ab, src) - dst).norm(dim=-1) <= gate_px
    src, dst = src[near], dst[near]
    if len(src) < min_inliers:
        return None, f"only {len(src)} consistent matches"
    model, inliers = ransac(src.float(), dst.float())
    count = int(inliers.sum())
    if count < min_inliers or not torch.isfinite(model).all() or float(model.abs().sum()) == 0.0:
        return None, f"RANSAC found {count} inliers"
    return (src[inliers], dst[inliers]), ""


def refine_homographies(views: Tensor, predicted: Tensor, gate_px: float = 40.0,
                        num_features: int = 1500, min_inliers: int = 20, inlier_px: float = 1.5,
                        seed: int = 0, intrinsics: Tensor | None = None) -> Refinement:
    """Estimate each side view's homography to the fovea's view from the images.

    The four edge cameras are matched with the fovea; each corner camera with the fovea and
    with its two edge neighbours, whose matches are carried into the fovea's pixel frame by
    the neighbours' refined homographies (exact: the cameras share a centre).

    Parameters
    ----------
    views : Tensor (9, H, W) float in [0, 1], the array's views (the fovea parked)
    predicted : Tensor (9, 3, 3), design homographies (view px -> fovea px) used as the prior
    gate_px : float
        How far (in pixels of these views) a match may land from the prediction; set it from
        the assembly tolerance (1 deg is about f / p * 0.0175 full-resolution pixels).
    num_features, min_inliers, inlier_px, seed
        SIFT features per view; the fewest RANSAC inliers per camera pair; RANSAC's inlier
        threshold in pixels; RANSAC's random seed.
    intrinsics : Tensor (3, 3) or None
        The views' K. Given, the final fit through the inliers is a pure rotation
        H = K R K^-1 (3 parameters: the cameras share a centre), which extrapolates far
        better beyond the small overlaps than a free homography (8 parameters, used when None).
    """
    if views.ndim != 3 or views.shape[0] != len(CAMERA_NAMES):
        raise HbisInputError(f"need the nine views (9, H, W), got {tuple(views.shape)}")
    if predicted.shape != (len(CAMERA_NAMES), 3, 3):
        raise HbisInputError("need nine predicted homographies (9, 3, 3)")
    if not torch.isfinite(views).all():
        raise HbisInputError("the views contain NaN or inf")
    shape = tuple(views.shape[1:])
    detector = KF.SIFTFeature(num_features=num_features, upright=True)
    ransac = RANSAC("homography", inl_th=inlier_px, max_iter=50, seed=seed)
    features = [_features(view, detector) for view in views]
    result = Refinement(homographies=predicted.clone().double(), inliers=[0] * 9, ok=[False] * 9)
    result.ok[FOVEA_INDEX] = True
    for name in EDGES + tuple(CORNER_NEIGHBOURS):
        k = CAMERA_NAMES.index(name)
        partners = [FOVEA_INDEX] + [CAMERA_NAMES.index(n) for n in CORNER_NEIGHBOURS.get(name, ())
                                    if result.ok[CAMERA_NAMES.index(n)]]
        sources, targets, why = [], [], []
        for j in partners:
            h_to_fovea = result.homographies[j]
            h_kj = torch.linalg.inv(h_to_fovea) @ predicted[k].double()
            pair, reason = _pair_matches(features[k], features[j], h_kj, shape, gate_px, ransac, min_inliers)
            if pair is None:
                why.append(f"{CAMERA_NAMES[j]}: {reason}")
                continue
            sources.append(pair[0])
            targets.append(apply_homography(h_to_fovea, pair[1]))  # into the fovea's pixel frame
        if not sources:
            result.messages.append(f"{name}: no usable matches ({'; '.join(why)}); design kept")
            continue
        src, dst = torch.cat(sources), torch.cat(targets)
        everything = torch.ones(len(src), dtype=torch.bool)
        if intrinsics is None:
            h = find_homography_dlt(src[None], dst[None])[0]
        else:
            h = _rotation_homography(src, dst, everything, intrinsics, inlier_px)
        result.homographies[k] = h / h[2, 2]
        result.inliers[k] = len(src)
        result.ok[k] = True
    return result
