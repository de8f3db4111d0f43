"""Hand-held bursts from a third renderer, written apart from the project's two, against the truth.

    python training/eval_third_renderer.py --out benchmarks/results/eval_third_renderer.json
        [--cells similarity:2:16 homography:4:16 ...] [--photos held-out|training] [--seed 0]
        [--size 640x480] [--blur 0.3] [--full-well 10000] [--colour] [--point-target] [--no-learned] [--no-vidsr]
        [--table-only]
        [--redo classical classical_lens learned]

The held-out matrix (training/eval_handheld.py) renders with the project's own second renderer
(:mod:`hbis_torch.training.handheld_render`). A result that holds only on one renderer may hold
on its conventions; this script renders bursts as an outside user's script would, sharing
nothing with the package but the photographs:

* **the scene** (:func:`scene`): photographs of scikit-image, each a tile of :data:`TILE_PX`
  output pixels *at their own scale* (one photograph pixel, one output pixel: the handheld
  renderer enlarges them 1.25 times), so the truth keeps each photograph's own softness and
  sharpening; the held-out photographs (``--photos held-out``, the default) or the training ones
  (``--photos training``: development data); grey, or in colour with ``--colour`` (the same
  crops, RGB; a grey photograph's three channels equal), each channel through the same optics
  and motion and its own noise;
* **the optics**: the scene enlarged :data:`FINE` times by OpenCV's bicubic ``resize`` (so its
  pixels are a quarter of an LR pixel at S = 2), blurred by a Gaussian lens of ``--blur`` LR px
  (``cv2.GaussianBlur``);
* **the pixel**: each frame pixel the mean of an n x n grid of points over its square (n = S x
  :data:`FINE`: the enlarged scene's pixel centres, for a frame that does not move), each point
  moved by the frame's homography and read from the enlarged scene by ``cv2.remap`` (bicubic);
* **the motion** (:func:`homographies`): turns about the frame's centre (``similarity`` and
  ``homography``: up to :data:`MAX_TURN_DEG`), a perspective moving a corner up to
  :data:`MAX_PERSPECTIVE_PX` (``homography``), shifts up to :data:`MAX_SHIFT_PX`; frame 0 the
  reference; and what no homography holds (:func:`effects`), each on a base motion
  (:data:`BASE`): ``rolling``, a rolling shutter (shifts, and each row moved further by the
  camera's speed times the row's read-out time, up to :data:`MAX_ROLL_PX` over the frame's
  height); ``object``, a disc of another photograph (:data:`OBJECT_RADIUS_LR` LR px) that moves
  steadily across the frames (:data:`OBJECT_SPEED_LR` LR px a frame), the truth holding it where
  the reference frame saw it; ``brightness``, each frame's exposure scaled by up to
  :data:`MAX_GAIN_CHANGE` (before the noise); ``shaken``, a quarter of the frames besides the
  reference smeared (a shake while the shutter was open: the enlarged scene blurred along a line
  of :data:`SHAKE_PX` LR px in a random direction, or by a Gaussian of :data:`SHAKE_SIGMA_PX`, in
  turn);
* **the noise**: Poisson of a full well of :data:`FULL_WELL_E` electrons (at mid grey 0.7 % of white;
  ``--full-well``: a dimmer light, 200 about 5 %) and Gaussian read noise of :data:`READ_E`, 16 bits.

The truth is the scene itself on the output grid (no lens: the lens is what the methods should
undo; the photographs' own softness is part of the scene). The scene ends at the reference
frame's edge: a frame that turns reads its mirror image (``BORDER_REFLECT``) within a few pixels
of its corners, which every method but bicubic sees; scored without 12 or 24 LR px of border
instead of 4, two cells checked (the misses of docs/real-bursts.md) kept every difference between
rows to a hundredth of a dB. Rows: bicubic, classical (the
defaults: ``hbis assemble --burst`` then ``hbis reconstruct --method classical``), with ``shaken``
cells classical_keep (every frame fused, ``--keep-blurred``), classical_lens
(the render's lens given, as ``--psf-sigma`` would), with ``--point-target`` classical_point (the
classical method aiming at the scene at the output pixels' centres, as this truth is, rather than at
the scene averaged over each output pixel: ``target_aperture=0``), learned, and the peer vidsr in its fidelity
setting (benchmarks/peers/vidsr_peer.py), scored by PSNR (over the three channels with
``--colour``) without 4 LR px of border. Each cell is written to ``--out`` when done; a run that
stops resumes at the next cell. At the end a summary (each difference's mean and worst, and the cells where classical trails vidsr by more than the
issue's 0.3 dB) goes into the JSON and, with the table, beside it as ``.md`` (``--table-only``
writes both again from a finished ``--out``). ``--redo ROW ...`` runs those rows again in the cells
``--out`` already holds and keeps the others (the peer's, bicubic's: rows a change of the project's
method leaves as they were; the cell's motion models come from the new assembly); the file then
lists every run's provenance, and each redone row names its run (``"run"``: the index in that list).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from eval_handheld import _peer, bicubic, psnr, runs_with

MOTIONS = ("translation", "similarity", "homography", "rolling", "object", "brightness", "shaken")
# the homographies under each motion that adds what no homography holds (:func:`effects`)
BASE = {"rolling": "translation", "object": "similarity", "brightness": "similarity", "shaken": "similarity"}
ROWS = ("bicubic", "classical", "classical_keep", "classical_lens", "classical_point", "learned", "vidsr")
DEFAULT_CELLS = ("translation:2:16", "similarity:2:16", "homography:2:16", "similarity:2:8",
                 "homography:2:8", "similarity:3:16", "homography:3:8", "homography:4:16")
TILE_PX = 280  # fits the smallest photograph (chelsea, 300 x 451)
FINE = 2  # enlarged scene's pixels per output pixel
MAX_SHIFT_PX, MAX_TURN_DEG, MAX_PERSPECTIVE_PX = 2.5, 0.7, 1.5
MAX_ROLL_PX = 1.5  # the rolling shutter's shift between the first row and the last, each axis
OBJECT_RADIUS_LR, OBJECT_SPEED_LR = 40, (1.0, 2.5)  # LR px; LR px a frame, drawn between
OBJECT_MARGIN_LR = 8  # the disc's edge at least this far inside the reference frame
MAX_GAIN_CHANGE = 0.07
SHAKE_PX, SHAKE_SIGMA_PX = (2.0, 4.0), (0.6, 1.2)  # LR px, each drawn between
FULL_WELL_E, READ_E = 10_000.0, 3.0
BORDER_LR = 4
PEER_GAP = 0.3  # the goal: classical never more than this behind vidsr in a cell
# The differences (a - b) the table shows and the summary takes the mean and worst of (with
# learned - vidsr too), where both rows were run.
DIFFERENCES = (("classical", "vidsr"), ("classical", "bicubic"), ("classical", "classical_keep"),
               ("classical_lens", "classical"), ("learned", "classical"), ("classical_point", "classical"))


def scene(height: int, width: int, photos, rng: np.random.Generator, colour: bool = False) -> np.ndarray:
    """Photographs (names of :mod:`skimage.data`; those smaller than a tile left out) in tiles of
    :data:`TILE_PX` px at their own scale, each a random crop of a random photograph: (height,
    width) float32 in [0, 1], or (height, width, 3) RGB with ``colour`` (the same crops)."""
    from skimage import color, data

    pictures = {}
    for name in photos:
        image = getattr(data, name)()
        if colour:
            picture = image[..., :3] / 255.0 if image.ndim == 3 else np.repeat(image[..., None] / 255.0, 3, -1)
        else:
            picture = color.rgb2gray(image[..., :3]) if image.ndim == 3 else image / 255.0
        if min(picture.shape[:2]) >= TILE_PX:  # (the training set's page and text are smaller)
            pictures[name] = picture
    out = np.zeros((height, width, 3) if colour else (height, width), np.float32)
    for y in range(0, height, TILE_PX):
        for x in range(0, width, TILE_PX):
            picture = pictures[str(rng.choice(sorted(pictures)))]
            th, tw = min(TILE_PX, height - y), min(TILE_PX, width - x)
            y0, x0 = rng.integers(0, picture.shape[0] - th + 1), rng.integers(0, picture.shape[1] - tw + 1)
            out[y:y + th, x:x + tw] = picture[y0:y0 + th, x0:x0 + tw]
    return out


def homographies(motion: str, count: int, width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3, 3) frame px -> reference px, pixel centres at integers; frame 0 the identity."""
    cx, cy = (width - 1) / 2, (height - 1) / 2
    centre = np.array([[1, 0, cx], [0, 1, cy], [0, 0, 1.0]])
    out = [np.eye(3)]
    for _ in range(count - 1):
        angle = np.deg2rad(rng.uniform(-MAX_TURN_DEG, MAX_TURN_DEG)) if motion != "translation" else 0.0
        turn = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        tilt = np.eye(3)
        if motion == "homography":  # a corner (about cx, cy from the centre) moves about MAX_PERSPECTIVE_PX
            tilt[2, :2] = rng.uniform(-1, 1, 2) * MAX_PERSPECTIVE_PX / (cx * cx + cy * cy)
        shift = np.eye(3)
        shift[:2, 2] = rng.uniform(-MAX_SHIFT_PX, MAX_SHIFT_PX, 2)
        out.append(shift @ centre @ tilt @ turn @ np.linalg.inv(centre))
    return np.stack(out)


def effects(motion: str, count: int, width: int, height: int, scale: int, photos,
            rng: np.random.Generator, colour: bool = False) -> dict:
    """What ``motion`` adds beyond its frames' homographies, per frame (frame 0 has none): ``roll``
    (count, 2), the rolling shutter's shift from the first row to the last (LR px); ``gain``
    (count,); ``object``, the disc's texture (its own photograph, (2 R S, 2 R S) output px), its
    centre in the reference frame (output px) and its move in each frame (count, 2) output px.
    Empty for the motions :func:`homographies` holds."""
    out = {}
    if motion == "rolling":
        out["roll"] = rng.uniform(-MAX_ROLL_PX, MAX_ROLL_PX, (count, 2))
        out["roll"][0] = 0
    elif motion == "shaken":  # the enlarged scene's blur (its px: S FINE a LR px), frame by frame
        frames = rng.choice(np.arange(1, count), size=max(1, (count - 1) // 4), replace=False)
        out["shake"] = {int(k): _shake_kernel(i % 2 == 0, scale * FINE, rng) for i, k in enumerate(sorted(frames))}
    elif motion == "brightness":
        out["gain"] = 1 + rng.uniform(-MAX_GAIN_CHANGE, MAX_GAIN_CHANGE, count)
        out["gain"][0] = 1
    elif motion == "object":
        radius = OBJECT_RADIUS_LR * scale
        speed = rng.uniform(*OBJECT_SPEED_LR) * scale
        angle = rng.uniform(0, 2 * np.pi)
        # a whole output px, so that the truth's disc is drawn on the grid as the frames' is
        inset = radius + OBJECT_MARGIN_LR * scale
        centre = np.array([rng.integers(inset, scale * width - inset),
                           rng.integers(inset, scale * height - inset)], float)
        out["object"] = (scene(2 * radius, 2 * radius, photos, rng, colour), centre,
                         np.arange(count)[:, None] * speed * np.array([np.cos(angle), np.sin(angle)]))
    return out


def _shake_kernel(line: bool, n: int, rng: np.random.Generator) -> np.ndarray:
    """A shake's blur on a grid of ``n`` px a LR px, normalised: a line of :data:`SHAKE_PX` LR px in
    a random direction (``line``), else a Gaussian of :data:`SHAKE_SIGMA_PX`."""
    import cv2

    if line:
        length, angle = rng.uniform(*SHAKE_PX) * n, rng.uniform(0, np.pi)
        half = int(np.ceil(length / 2)) + 1
        kernel = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
        dx, dy = np.cos(angle) * length / 2, np.sin(angle) * length / 2
        cv2.line(kernel, (round(half - dx), round(half - dy)), (round(half + dx), round(half + dy)), 1.0, 1,
                 cv2.LINE_AA)
    else:
        sigma = rng.uniform(*SHAKE_SIGMA_PX) * n
        half = int(np.ceil(3 * sigma))
        axis = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
        kernel = np.outer(axis, axis).astype(np.float32)
    return kernel / kernel.sum()


def _with_object(background: np.ndarray, texture: np.ndarray, centre: np.ndarray, move: np.ndarray) -> np.ndarray:
    """``background`` (output px) with the disc of ``texture`` centred at ``centre + move``
    (output px), its edge anti-aliased over one output px."""
    import cv2

    radius = texture.shape[0] / 2
    x0, y0 = centre + move - radius  # the texture's corner on the background
    placed = cv2.warpAffine(texture, np.float32([[1, 0, x0], [0, 1, y0]]), background.shape[1::-1],
                            flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    ys, xs = np.mgrid[0:background.shape[0], 0:background.shape[1]]
    # (texture px centres at integers: its centre is at radius - 1/2)
    distance = np.hypot(xs - (centre[0] + move[0] - 0.5), ys - (centre[1] + move[1] - 0.5))
    inside = np.clip(radius - distance + 0.5, 0, 1).astype(np.float32)
    if background.ndim == 3:
        inside = inside[..., None]
    return background * (1 - inside) + placed * inside


def render(motion: str, scale: int, count: int, width: int, height: int, seed: int, photos,
           blur: float = 0.3, noise: bool = True, colour: bool = False,
           full_well: float = FULL_WELL_E) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A burst: (frames (F, H, W) uint16 (float64 in [0, 1] without ``noise``), truth (S H, S W)
    float32, homographies (F, 3, 3)); with ``colour`` the frames (F, H, W, 3) and the truth
    (S H, S W, 3), RGB; ``full_well``: electrons at white."""
    rng = np.random.default_rng(seed)
    truth = scene(scale * height, scale * width, photos, rng, colour)
    motions = homographies(BASE.get(motion, motion), count, width, height, rng)
    extra = effects(motion, count, width, height, scale, photos, rng, colour)
    background = truth
    if "object" in extra:
        texture, centre, moves = extra["object"]
        truth = _with_object(background, texture, centre, moves[0])
    fine = _enlarged(truth, scale, blur)
    frames = []
    for k, m in enumerate(motions):
        if "object" in extra and k > 0:
            fine = _enlarged(_with_object(background, texture, centre, moves[k]), scale, blur)
        roll = extra["roll"][k] if "roll" in extra else None
        seen = fine
        if k in extra.get("shake", {}):
            import cv2

            seen = cv2.filter2D(fine, -1, extra["shake"][k], borderType=cv2.BORDER_REFLECT)
        frame = _integrated(seen, m, roll, scale, width, height) * (extra["gain"][k] if "gain" in extra else 1)
        frame = np.clip(frame, 0, 1)
        if noise:
            electrons = rng.poisson(frame * full_well) + rng.normal(0, READ_E, frame.shape)
            frame = np.clip(np.round(electrons / full_well * 65535), 0, 65535).astype(np.uint16)
        frames.append(frame)
    return np.stack(frames), truth, motions


def _enlarged(scene_px: np.ndarray, scale: int, blur: float) -> np.ndarray:
    """The scene (output px) enlarged :data:`FINE` times (bicubic) and blurred by the lens
    (``blur`` LR px)."""
    import cv2

    n = scale * FINE  # enlarged-scene px per LR px
    height, width = scene_px.shape[0] // scale, scene_px.shape[1] // scale
    fine = cv2.resize(scene_px, (n * width, n * height), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(fine, (0, 0), blur * n) if blur > 0 else fine


def _integrated(fine: np.ndarray, m: np.ndarray, roll, scale: int, width: int, height: int) -> np.ndarray:
    """A frame (height, width) float64: each pixel the mean of an n x n grid of points over its
    square, each moved by the homography ``m`` (and by ``roll`` (2,) LR px times its pixel row's
    place between the first row and the last: a row is read at once) and read from the enlarged
    scene ``fine`` (bicubic)."""
    import cv2

    n = scale * FINE
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    total = np.zeros((height, width, *fine.shape[2:]))
    for a in range(n):
        for b in range(n):
            u, v = xs + (b + 0.5) / n - 0.5, ys + (a + 0.5) / n - 0.5
            w = m[2, 0] * u + m[2, 1] * v + m[2, 2]
            x, y = (m[0, 0] * u + m[0, 1] * v + m[0, 2]) / w, (m[1, 0] * u + m[1, 1] * v + m[1, 2]) / w
            if roll is not None:  # the pixel row's read-out time (one per row), centred on the middle row
                x, y = x + roll[0] * (ys / (height - 1) - 0.5), y + roll[1] * (ys / (height - 1) - 0.5)
            # LR px -> the enlarged scene's px (centres at (i + 1/2) / n - 1/2 LR px)
            total += cv2.remap(fine, (n * (x + 0.5) - 0.5).astype(np.float32), (n * (y + 0.5) - 0.5).astype(np.float32),
                               cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return total / (n * n)


def run_cell(motion: str, scale: int, count: int, args, rows=None) -> dict:
    """One cell's rows (``rows``, default all of ``args.rows``): PSNR, seconds, and the classical
    method's notes."""
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import reconstruct

    frames, truth, _ = render(motion, scale, count, args.width, args.height, args.seed, args.photo_names, args.blur,
                              colour=args.colour, full_well=args.full_well)
    stack, assemble_messages = assemble_burst(frames, scale)
    out = {"models": list(stack.meta["motion_models"]), "assemble_messages": assemble_messages}
    for row in args.rows if rows is None else rows:
        started, notes = time.perf_counter(), []
        if row == "bicubic":
            image = bicubic(frames[0], scale)
        elif row == "vidsr":
            image = _peer().vidsr_sr(frames, scale)
        elif row == "classical_keep":
            image = reconstruct(stack, "classical", messages=notes, keep_blurred=True)
        elif row == "classical_lens":
            image = reconstruct(stack, "classical", messages=notes, lens_sigma=args.blur)
        elif row == "classical_point":
            image = reconstruct(stack, "classical", messages=notes, target_aperture=0.0)
        else:
            image = reconstruct(stack, row, messages=notes)
        out[row] = {"psnr_db": psnr(image, truth, BORDER_LR, scale), "seconds": time.perf_counter() - started,
                    "messages": notes}
    return out


def table(cells: dict, rows) -> str:
    """The Markdown table of the cells, with the differences the issue's goals name."""
    head = ["motion", "S", "F", *rows]
    pairs = [(a, b) for a, b in DIFFERENCES if a in rows and b in rows]
    head += [f"{a} - {b}" for a, b in pairs]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for key, cell in cells.items():
        motion, scale, count = key.split(":")
        values = [f"{cell[r]['psnr_db']:.2f}" for r in rows]
        values += [f"{cell[a]['psnr_db'] - cell[b]['psnr_db']:+.2f}" for a, b in pairs]
        lines.append("| " + " | ".join([motion, scale, count, *values]) + " |")
    return "\n".join(lines) + "\n"


def summary(cells: dict, rows) -> dict:
    """Over the cells: each difference of :func:`table`'s mean and worst (dB), and the cells where
    classical trails vidsr by more than :data:`PEER_GAP` (the issue's goal)."""
    out = {}
    for a, b in (*DIFFERENCES, ("learned", "vidsr")):
        if a in rows and b in rows:
            gaps = [cell[a]["psnr_db"] - cell[b]["psnr_db"] for cell in cells.values()]
            out[f"{a}_minus_{b}"] = {"mean_db": float(np.mean(gaps)), "worst_db": float(np.min(gaps))}
    if "vidsr" in rows:
        out["classical_behind_vidsr_by_more_than_gap"] = [
            key for key, cell in cells.items() if cell["classical"]["psnr_db"] - cell["vidsr"]["psnr_db"] < -PEER_GAP]
    return out


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="results JSON (resumed if it exists); a .md beside it")
    p.add_argument("--cells", nargs="+", default=list(DEFAULT_CELLS), metavar="MOTION:S:F",
                   help=f"cells, each MOTION:S:F, MOTION one of {', '.join(MOTIONS)} (default: {' '.join(DEFAULT_CELLS)})")
    p.add_argument("--photos", choices=("held-out", "training"), default="held-out",
                   help="the held-out photographs (default) or the training ones (development data)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", default="640x480", help="frames' WxH (default 640x480)")
    p.add_argument("--blur", type=float, default=0.3, help="the lens's Gaussian sigma, LR px (default 0.3)")
    p.add_argument("--full-well", type=float, default=FULL_WELL_E,
                   help=f"electrons at white (default {FULL_WELL_E:g}: 0.7 %% noise at mid grey); fewer is a "
                        "dimmer light: 200 about 5 %%")
    p.add_argument("--colour", action="store_true", help="RGB bursts (the same photographs' crops in colour), "
                   "reconstructed with the methods' colour defaults and scored over the three channels")
    p.add_argument("--point-target", action="store_true", help="also classical_point: the classical method aiming at "
                   "the scene at the output pixels' centres, as the truth here is (target_aperture=0), not at its "
                   "average over each output pixel (the default's target)")
    p.add_argument("--no-learned", action="store_true")
    p.add_argument("--no-vidsr", action="store_true")
    p.add_argument("--table-only", action="store_true", help="write the summary and the .md from --out alone")
    p.add_argument("--redo", nargs="+", default=[], metavar="ROW",
                   help="run these rows again in the cells --out holds, keeping its other rows (the peer's)")
    args = p.parse_args(argv)
    problem = None
    try:
        args.width, args.height = (int(v) for v in args.size.lower().split("x"))
        parsed = [(m, int(s), int(f)) for m, s, f in (c.split(":") for c in args.cells)]
    except ValueError:
        problem, parsed = f"--size takes WxH and --cells MOTION:S:F, got {args.size!r} and {args.cells}", []
    if problem is None and min(args.width, args.height) < 64:
        problem = "--size: 64 px or more each way"
    bad = [c for c, (m, s, f) in zip(args.cells, parsed) if m not in MOTIONS or not 2 <= s <= 4 or f < 2]
    if problem is None and bad:
        problem = f"--cells {' '.join(bad)}: MOTION one of {', '.join(MOTIONS)}, S 2 to 4, F 2 or more"
    object_side = 2 * (OBJECT_RADIUS_LR + OBJECT_MARGIN_LR) + 1
    if problem is None and any(m == "object" for m, _, _ in parsed) and min(args.width, args.height) < object_side:
        problem = f"--size {args.size}: object cells need {object_side} px or more each way (the disc and its margin)"
    if problem is None and not args.out.parent.is_dir():
        problem = f"--out {args.out}: the folder does not exist"
    if problem is None and not 0 <= args.blur <= 2:
        problem = f"--blur {args.blur}: 0 to 2 LR px"
    if problem is None and not 10 <= args.full_well <= 1e6:
        problem = f"--full-well {args.full_well:g}: 10 to 1e6 electrons"
    if problem is None and args.table_only and not args.out.is_file():
        problem = f"--table-only: {args.out} does not exist"
    if problem is None and args.redo and (not args.out.is_file() or not set(args.redo) <= set(_rows(args))):
        problem = f"--redo {' '.join(args.redo)}: rows of this run ({', '.join(_rows(args))}) in an --out that exists"
    if problem is None and not args.table_only and args.out.is_file() and _settings(args) != \
            json.loads(args.out.read_text()).get("settings"):
        problem = f"--out {args.out} holds a run of other settings: name another file (it is not overwritten)"
    if problem is None and not args.no_vidsr and not args.table_only and not _peer().available():
        problem = "vidsr is not installed (pip install vidsr), or pass --no-vidsr"
    if problem:
        print(f"eval_third_renderer: {problem}", file=sys.stderr)
        raise SystemExit(2)
    args.parsed = parsed
    args.rows = _rows(args)
    from hbis_torch.simulate.rasters import HELD_OUT_PHOTOS
    from hbis_torch.training.data import TRAIN_PHOTOS

    args.photo_names = HELD_OUT_PHOTOS if args.photos == "held-out" else TRAIN_PHOTOS
    return args


def _settings(args) -> dict:
    """What a results file's cells depend on besides the cell: a run resumes only a file of the same."""
    out = {"photos": args.photos, "seed": args.seed, "size": [args.width, args.height], "blur": args.blur,
           "rows": _rows(args)}
    if args.full_well != FULL_WELL_E:  # (files of the default light name none)
        out["full_well_e"] = args.full_well
    return {**out, "colour": True} if args.colour else out  # (grey runs' files name no colour)


def _rows(args) -> list:
    shaken = any(cell.split(":")[0] == "shaken" for cell in args.cells)
    return [r for r in ROWS if not (r == "learned" and args.no_learned) and not (r == "vidsr" and args.no_vidsr)
            and not (r == "classical_point" and not args.point_target) and not (r == "classical_keep" and not shaken)]


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    from hbis_torch.provenance import provenance, write_results

    settings, done, prov = _settings(args), {}, None
    if args.out.exists():  # (parse_args refused a file of other settings)
        previous = json.loads(args.out.read_text())
        settings, done = previous["settings"], previous["cells"]
        prov = previous["provenance"] if args.table_only else None
        args.rows = settings["rows"]
        if args.redo:
            prov = runs_with(previous["provenance"], provenance(argv=argv))
    todo = [] if args.table_only else [(cell, key) for cell, key in zip(args.parsed, args.cells) if key not in done]
    redo = [(cell, key) for cell, key in zip(args.parsed, args.cells) if key in done and args.redo
            and any(done[key][row].get("run") != len(prov) - 1 for row in args.redo)]  # (a stopped run resumes)
    for (motion, scale, count), key in redo:
        again = run_cell(motion, scale, count, args, rows=args.redo)
        done[key].update({"models": again["models"], "assemble_messages": again["assemble_messages"],
                          **{row: {**again[row], "run": len(prov) - 1} for row in args.redo}})
        print(key, "redone", {r: round(done[key][r]["psnr_db"], 2) for r in args.redo}, flush=True)
        write_results(args.out, {"settings": settings, "cells": done}, prov=prov)
    for (motion, scale, count), key in todo:
        done[key] = run_cell(motion, scale, count, args)
        print(key, {r: round(done[key][r]["psnr_db"], 2) for r in args.rows}, flush=True)
        write_results(args.out, {"settings": settings, "cells": done}, argv=argv, prov=prov)
    results = {"settings": settings, "cells": done, "summary": summary(done, args.rows)}
    prov = write_results(args.out, results, argv=argv, prov=prov)
    text = table(done, args.rows) + "\n" + "\n".join(f"- {k}: {v}" for k, v in results["summary"].items()) + "\n"
    if isinstance(prov, list):
        text += "\nRuns (a redone row names its run): " + "; ".join(
            f"{i}: `{run['command']}` at {run['commit'][:10]}, {run['date']}" for i, run in enumerate(prov)) + "\n"
    write_results(args.out.with_suffix(".md"), text, prov=prov[-1] if isinstance(prov, list) else prov)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
