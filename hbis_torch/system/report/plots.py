"""Pictures of the array's results: the views, the panorama (as the paper's Fig. 8a), the
composite, the super-resolved fovea beside a sub-image (Figs. 8b and 9), and the event timeline.

Every file is written atomically (``io_utils.atomic_path``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Polygon, Rectangle
from PIL import Image

from hbis_torch.io_utils import atomic_path
from hbis_torch.system.array.cameras import CAMERA_NAMES

#: The paper's Fig. 8a marks these four cameras' fields with coloured dashed outlines.
OUTLINE_COLOURS = {"C12": "tab:red", "C21": "tab:green", "C23": "tab:blue", "C32": "tab:orange"}


def save_png(image, path) -> Path:
    """Write a grey image (H, W) in [0, 1] as an 8-bit PNG."""
    array = np.clip(np.asarray(image, dtype=np.float32), 0.0, 1.0)
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(np.round(array * 255).astype(np.uint8)).save(tmp, format="PNG")
    return path


def save_figure(fig, path, dpi: int = 110) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", bbox_inches="tight")
    return path


def plot_views(views, path, title: str) -> Path:
    """The nine views in their array positions."""
    fig = Figure(figsize=(10, 7.6))
    axes = fig.subplots(3, 3)
    for ax, view, name in zip(axes.flat, views, CAMERA_NAMES):
        ax.imshow(np.asarray(view), cmap="gray", vmin=0, vmax=1)
        ax.set_title(name + (" (fovea, parked)" if name == "C22" else ""), fontsize=9)
        ax.axis("off")
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_panorama(image, outlines, path, title: str, rectangle=None, inlay_outline=None) -> Path:
    """The stitched panorama with the side cameras' outlines (dashed, as Fig. 8a), the
    largest covered rectangle (dotted) and the fovea's inlay (solid)."""
    image = np.asarray(image)
    fig = Figure(figsize=(11, 11 * image.shape[0] / image.shape[1] + 0.6))
    ax = fig.subplots()
    ax.imshow(image, cmap="gray", vmin=0, vmax=1)
    for name, corners in zip(CAMERA_NAMES, np.asarray(outlines)):
        colour = OUTLINE_COLOURS.get(name)
        if colour is None:
            continue
        ax.add_patch(Polygon(corners, closed=True, fill=False, ls="--", lw=1.6, ec=colour, label=name))
    if rectangle is not None:
        x0, x1, y0, y1 = rectangle
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ls=":", lw=1.4, ec="yellow",
                               label="largest covered rectangle"))
    if inlay_outline is not None:
        ax.add_patch(Polygon(np.asarray(inlay_outline), closed=True, fill=False, lw=1.6, ec="magenta",
                             label="fovea SR region"))
    ax.set_xlim(0, image.shape[1])
    ax.set_ylim(image.shape[0], 0)
    ax.legend(loc="lower right", fontsize=8, framealpha=0.8)
    ax.set_title(title)
    ax.axis("off")
    return save_figure(fig, path)


def plot_sr_pairs(sr, sub_image, h: int, path, title: str, boxes=None, truth=None) -> Path:
    """The SR fovea with numbered boxes, and each box beside the same region of one sub-image
    (the reference frame, nearest-neighbour enlarged h times), as the paper's Figs. 8b and 9."""
    sr = np.asarray(sr)
    big = np.kron(np.asarray(sub_image), np.ones((h, h), dtype=np.float32))
    if boxes is None:
        side = max(16, min(sr.shape) // 4)
        boxes = [(sr.shape[1] // 2 - side // 2, sr.shape[0] // 2 - side // 2, side, side),
                 (sr.shape[1] // 8, sr.shape[0] // 8, side, side),
                 (sr.shape[1] * 5 // 8, sr.shape[0] * 5 // 8, side, side)]
    columns = 3 if truth is not None else 2
    fig = Figure(figsize=(4.2 + 2.2 * columns, 6.6))
    grid = fig.add_gridspec(len(boxes), 1 + columns, width_ratios=[len(boxes)] + [1] * columns)
    ax = fig.add_subplot(grid[:, 0])
    ax.imshow(sr, cmap="gray", vmin=0, vmax=1)
    for k, (x, y, w, hh) in enumerate(boxes, 1):
        ax.add_patch(Rectangle((x - 0.5, y - 0.5), w, hh, fill=False, ec="red", lw=1.3))
        ax.text(x, y - 4, str(k), color="red", fontsize=10)
    ax.set_title("(a) super-resolved fovea")
    ax.axis("off")
    for k, (x, y, w, hh) in enumerate(boxes):
        panels = [(sr, "SR"), (big, "sub-image")] + ([(np.asarray(truth), "truth")] if truth is not None else [])
        for c, (img, label) in enumerate(panels):
            a = fig.add_subplot(grid[k, 1 + c])
            a.imshow(img[y:y + hh, x:x + w], cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            a.set_title(f"{k + 1}: {label}", fontsize=9)
            a.axis("off")
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_timeline(events, path, truth_x=None, title: str = "two-stage operation") -> Path:
    """Stage against simulated time, the events marked, and the object's x (truth and track)."""
    fig = Figure(figsize=(11, 5.6))
    ax1, ax2 = fig.subplots(2, 1, sharex=True, height_ratios=[1, 2])
    t = [e.t_s for e in events]
    ax1.step(t, [e.stage for e in events], where="post", color="black")
    ax1.set_yticks([1, 2], ["stage one", "stage two"])
    ax1.set_ylim(0.6, 2.4)
    styles = {"detected": ("o", "tab:blue"), "pointed": ("^", "tab:green"), "scan_started": ("s", "tab:orange"),
              "super_resolved": ("*", "tab:red"), "scan_discarded": ("x", "tab:gray"),
              "object_left": ("v", "tab:purple")}
    for kind, (marker, colour) in styles.items():
        pts = [(e.t_s, e.stage) for e in events if e.kind == kind]
        if pts:
            ax1.plot(*zip(*pts), marker, color=colour, label=kind.replace("_", " "), ms=7)
    ax1.legend(ncol=6, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, 1.35))
    if truth_x is not None:
        ax2.plot(truth_x[0], truth_x[1], color="black", lw=1, label="object x (truth)")
    pts = [(e.t_s, e.data["object_mm"][0]) for e in events if e.kind == "pointed"]
    if pts:
        ax2.plot(*zip(*pts), "^", color="tab:green", label="fovea pointed at x")
    pts = [(e.t_s, e.data["point_mm"][0]) for e in events if "point_mm" in e.data]
    if pts:
        ax2.plot(*zip(*pts), "o", color="tab:blue", label="detections / exit")
    for e in events:
        if e.kind == "super_resolved":
            ax2.axvline(e.t_s, color="tab:red", ls=":", lw=1)
    ax2.set_xlabel("simulated time [s]")
    ax2.set_ylabel("x on the scene plane [mm]")
    ax2.legend(fontsize=8)
    fig.suptitle(title)
    return save_figure(fig, path)
