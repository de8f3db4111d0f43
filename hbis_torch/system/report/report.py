"""The demo's one-page HTML report: every picture it wrote, the measured numbers beside the
paper's and the theory's, and the two-stage loop's event log.

The page is plain HTML with inline CSS and relative image links, so the output folder can be
moved or zipped and still opens in any browser. :func:`image_links` lists the images a page
names (the tests check that each exists).
"""

from __future__ import annotations

import html
import re
import shlex
import sys
from datetime import datetime, timezone
from pathlib import Path

from hbis_torch.io_utils import atomic_write_text

_CSS = """
body { font-family: system-ui, sans-serif; max-width: 1180px; margin: 1.5em auto; padding: 0 1em;
       color: #222; line-height: 1.4; }
h1 { margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
td, th { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; vertical-align: top; }
th { background: #f2f2f2; }
figure { margin: 0.8em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
.pair { display: flex; gap: 1em; flex-wrap: wrap; } .pair figure { flex: 1 1 45%; }
.pair figure img { width: 100%; } img.pixels { image-rendering: pixelated; }
.note { font-size: 0.9em; color: #555; }
.meta { font-size: 0.85em; color: #555; margin-top: 0; } .meta code { font-size: 0.95em; }
.summary { background: #f6f8fa; border: 1px solid #d0d7de; border-radius: 6px; padding: 0.4em 1em 0.8em; }
.summary h2 { margin-top: 0.4em; } .summary table { font-size: 1em; background: #fff; }
.summary td:nth-child(2) { font-weight: 600; }
"""

#: Captions of the figures ``hbis figures`` draws, by file name (a file not listed: its stem).
FIGURE_CAPTIONS = {
    "fig3_scan_patterns.png": "Fig. 3: the h x h sub-pixel scan patterns (raster order, x fastest), frames "
    "numbered from 0 as in the stack; green: the reference frame, taken at the initial phases.",
    "fig4_fov_fer.png": "Fig. 4: the whole FOV (left axis) and the FOV extension ratio FER = FOV / 2θ "
    "(right axis: the same curve read in FER) against the wedge angle a and the refractive index n; shaded: "
    "from φ = θ up to the largest inclination without a blind zone.",
    "fig5_max_ae.png": "Fig. 5: the largest alignment error of the optical axis with the paper's inverse "
    "(eqs. 8-9), h = 7, against φ2 for three φ1, against the wedge angle and against the index; the exact "
    "inverse's worst value is quoted on each panel.",
    "fig6_bsr.png": "Fig. 6: the bandwidth saving ratio (eq. 10) at the FER limits, one curve per h, against "
    "the wedge angle and the refractive index.",
    "fig10_fov_layout.png": "Fig. 10: the FOV of the eight periphery cameras (blue, labelled C_row,col) and the "
    "fovea's scan field (red: its FOV with the prisms aligned at every phase; dashed: its axis at full "
    "deviation), for the two design cases.",
    "scan_pixel_ae.png": "The pixel alignment error, worst over the 7 x 7 scan with the paper's inverse, for "
    "the three example initial phases (sensor convention).",
}


def figure_caption(path: str) -> str:
    """The caption of a figure file (:data:`FIGURE_CAPTIONS`, else its file stem)."""
    return FIGURE_CAPTIONS.get(Path(path).name, Path(path).stem.replace("_", " "))


def run_info(command: list[str] | None = None) -> dict:
    """Version, UTC date and command line of this run, for the report's header."""
    from hbis_torch import __version__

    argv = list(sys.argv if command is None else command)
    if argv:
        first = Path(argv[0])
        argv[0] = "hbis" if first.name == "hbis" or first.parent.name == "hbis_torch" else first.name
    return {"version": __version__, "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "command": shlex.join(argv)}


def _summary(s: dict) -> str:
    """The headline numbers: FER, foveal ratio, BSR, SR PSNR and the run's timings."""
    fer, theory = s["fer"]["measured_refined"]["rectangle"], s["fer"]["theory"]
    paper = s["fer"]["paper_prototype_measured"]
    bw, sr, cfg = s["bandwidth"], s["sr"], s["config"]
    rows = [
        ["FER, horizontal / vertical", f"{fer['fer_h']:.2f} / {fer['fer_v']:.2f}",
         f"theory {theory['fer_h']:.2f} / {theory['fer_v']:.2f}; paper's prototype {paper['h']} / {paper['v']}"],
        ["foveal ratio", f"{s['foveal_ratio']['measured']:.2f}", f"theory {s['foveal_ratio']['theory']} (= h)"],
        ["bandwidth saving ratio (BSR)", f"{bw['bsr_from_coverage']:.3f}",
         f"eq. 10 with the design FER {bw.get('bsr_eq10_design_fer', float('nan')):.3f}"],
    ]
    if "psnr_sr_db" in sr:
        versus = f"bicubic {sr['psnr_bicubic_db']:.2f} dB"
        if "psnr_classical_db" in sr and cfg["method"] != "classical":
            versus += f", classical {sr['psnr_classical_db']:.2f} dB"
        rows.append([f"SR PSNR, {cfg['method']} (h = {cfg['h']})", f"{sr['psnr_sr_db']:.2f} dB",
                     f"{versus} (against the ground truth)"])
    timings = s.get("timings_s", {})
    if timings:
        slowest = sorted(timings.items(), key=lambda kv: -kv[1])[:3]
        rows.append(["time of the chain", f"{sum(timings.values()):.1f} s",
                     ", ".join(f"{k} {v:.1f} s" for k, v in slowest)])
    return ("<section class='summary'><h2>Summary</h2>"
            + _table(["measure", "this run", "for comparison"], rows) + "</section>")



def _fmt(value, digits: int = 3) -> str:
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return html.escape(str(value))


def _table(header: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _figure(src: str, caption: str, pixels: bool = False) -> str:
    klass = ' class="pixels"' if pixels else ""
    return (f'<figure><img{klass} src="{html.escape(src)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def image_links(page: str) -> list[str]:
    """The ``src`` of every <img> in an HTML page."""
    return re.findall(r'<img[^>]*\ssrc="([^"]+)"', page)


def render_report(summary: dict, design_report: dict, design_figures: list[str], run: dict | None = None) -> str:
    """The report page as a string (see :func:`write_report`); ``run``: :func:`run_info`."""
    s, img = summary, summary["images"]
    fer, theory = s["fer"]["measured_refined"], s["fer"]["theory"]
    design_fer = s["fer"]["measured_design_stitch"]
    paper = s["fer"]["paper_prototype_measured"]
    bw, sr, cfg = s["bandwidth"], s["sr"], s["config"]
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<title>HBIS demo report</title>", f"<style>{_CSS}</style></head><body>",
        "<h1>HBIS demo: FOV extension and foveated super-resolution</h1>",
        _meta(run),
        _summary(s),
        f"<p class='note'>A simulated 3 x 3 hybrid bionic image sensor (Table 1 cameras, φ<sub>h</sub> = "
        f"{cfg['varphi_h_deg']:g}°, φ<sub>v</sub> = {cfg['varphi_v_deg']:g}°, side cameras misassembled by "
        f"{cfg['assembly_sigma_deg']:g} deg rms) watches a wall of photographs. A sign moves in, stops and leaves; "
        f"the periphery detects it, the Risley fovea is steered onto it and super-resolves it (h = {cfg['h']}, "
        f"method <b>{html.escape(cfg['method'])}</b>). Panorama views are binned {s['binning']['panorama']} x "
        f"{s['binning']['panorama']}, detection frames {s['binning']['detection']} x {s['binning']['detection']}; "
        "the fovea's scan frames are full resolution.</p>",
        "<h2>Stitched panorama (paper Fig. 8a)</h2>",
        _figure(img["panorama_figure"], "Nine views stitched with homographies refined from the images "
                "(SIFT + RANSAC, rotation model). Dashed: C12, C21, C23, C32; dotted: the largest covered "
                "rectangle; magenta: the super-resolved fovea."),
        "<div class='pair'>",
        _figure(img["panorama_design"], "The same views stitched with the design angles only: the "
                "assembly errors show as doubled edges."),
        _figure(img["views"], "The nine camera views (C22 is the fovea, parked)."),
        "</div>",
        "<h3>FOV extension ratio</h3>",
        _table(["", "FER_h", "FER_v", "FOV_h [deg]", "FOV_v [deg]"], [
            ["measured, largest covered rectangle", fer["rectangle"]["fer_h"], fer["rectangle"]["fer_v"],
             fer["rectangle"]["fov_h_deg"], fer["rectangle"]["fov_v_deg"]],
            ["measured, through the optical axis", fer["central"]["fer_h"], fer["central"]["fer_v"],
             fer["central"]["fov_h_deg"], fer["central"]["fov_v_deg"]],
            ["design-angle stitch (no assembly error), rectangle", design_fer["rectangle"]["fer_h"],
             design_fer["rectangle"]["fer_v"], design_fer["rectangle"]["fov_h_deg"],
             design_fer["rectangle"]["fov_v_deg"]],
            ["theory, 2 (φ + θ) / 2θ", theory["fer_h"], theory["fer_v"], theory["fov_h_deg"],
             theory["fov_v_deg"]],
            ["paper: prototype measured (theory 2.3 / 2.2)", paper["h"], paper["v"], "49", "34"],
        ]),
        "<p>The same measures over random assemblies (12 each, side cameras misaligned by sigma rms, "
        "stitched with their true homographies):</p>",
        _table(["sigma [deg]", "rectangle FER_h mean (min)", "rectangle FER_v mean (min)",
                "central FER_h mean", "central FER_v mean"],
               [[f"{a['sigma_deg']:g}", f"{a['rectangle_fer_h_mean']:.3f} ({a['rectangle_fer_h_min']:.3f})",
                 f"{a['rectangle_fer_v_mean']:.3f} ({a['rectangle_fer_v_min']:.3f})", a["central_fer_h_mean"],
                 a["central_fer_v_mean"]] for a in s["fer"].get("assembly_study", [])]),
        f"<p class='note'>Stitching error against the true assembly (worst view corner, sensor pixels): "
        f"design angles {_fmt(s['refinement'].get('design_error_px', float('nan')), 1)}, refined "
        f"{_fmt(s['refinement'].get('refined_error_px', float('nan')), 2)}.</p>",
        "<h2>Foveated composite</h2>",
        "<div class='pair'>",
        _figure(img["panorama"], "The stitched panorama as the periphery sees it."),
        _figure(img["composite"], "The same with the super-resolved fovea inlaid at its true place "
                "and scale (traced back through the prisms)."),
        "</div>",
        _figure(img["composite_zoom"], f"Zoom on the fovea at one SR pixel per image pixel: the inlay "
                f"(h = {cfg['h']}) inside the bicubically enlarged periphery."),
        _table(["", "measured", "theory / eq. 10"], [
            ["foveal ratio (sampling frequency, fovea / periphery)", s["foveal_ratio"]["measured"],
             s["foveal_ratio"]["theory"]],
            ["BSR, eq. 10's accounting with the measured whole-FOV area", bw["bsr_from_coverage"],
             bw.get("bsr_eq10_design_fer", float("nan"))],
            ["BSR, eq. 10 with the measured FER (rectangle)", bw["bsr_eq10_measured_fer"],
             bw.get("bsr_eq10_design_fer", float("nan"))],
            ["BSR, this demo's traffic (9 raw frames + ROI scan) vs uniform h-times capture",
             bw["bsr_demo_traffic"], "-"],
        ]),
        f"<p class='note'>Whole FOV = {bw['whole_fov_frames']:.2f} sensor frames; a uniform capture at the "
        f"fovea's sampling needs {bw['uniform_capture_px']:.3g} pixels, eq. 10's accounting transmits "
        f"{bw['eq10_traffic_px']:.3g}, this demo transmitted {bw['demo_traffic_px']:.3g}.</p>",
        "<h2>Super-resolved fovea beside a sub-image (paper Figs. 8b and 9)</h2>",
        _figure(img["sr_pairs"], "Left: the SR fovea; right: three regions of it beside the same regions "
                "of the reference sub-image (enlarged) and the ground truth."),
        "<div class='pair'>",
        _figure(img["sr_fovea"], f"SR fovea, {sr['shape'][1]} x {sr['shape'][0]} pixels."),
        _figure(img["sub_image"], f"Reference sub-image, ROI {sr['roi']} (u0, v0, width, height), "
                "shown at the same size.", pixels=True),
        "</div>",
    ]
    if "psnr_sr_db" in sr:
        parts.append(f"<p>PSNR against the ground truth: SR {sr['psnr_sr_db']:.2f} dB, bicubic enlargement "
                     f"of the sub-image {sr['psnr_bicubic_db']:.2f} dB.</p>")
    parts += [
        "<h2>Two-stage operation (paper section 2.1)</h2>",
        _figure(img["timeline"], "Stage against simulated time, with the events; below, the object's "
                "true x and where the system detected and pointed at it."),
        "<details><summary>Event log</summary>",
        _table(["t [s]", "stage", "event", "what happened"],
               [[e["t_s"], e["stage"], e["kind"], e["message"]] for e in s["events"]]),
        "</details>",
        "<h2>The paper's figures (design, scanning)</h2>",
        _table(["quantity", "value"], [
            ["one camera's FOV [deg]", f"{design_report['single_fov_h_deg']:.1f} x {design_report['single_fov_v_deg']:.1f}"],
            ["φ limits [deg]", f"h <= {design_report['varphi_h_max_deg']:.2f}, v <= {design_report['varphi_v_max_deg']:.2f}"],
            ["H (diffraction), h_max", f"{design_report['H']:.2f}, {design_report['h_max']}"],
        ]),
    ]
    parts += [_figure(f, figure_caption(f)) for f in design_figures]
    parts += [
        "<h2>Run</h2>",
        _table(["step", "seconds"], [[k, v] for k, v in s["timings_s"].items()]),
        "</body></html>",
    ]
    return "\n".join(parts)


def _meta(run: dict | None) -> str:
    if not run:
        return ""
    return (f"<p class='meta'>hbis-torch {html.escape(str(run['version']))} · {html.escape(run['date'])} · "
            f"<code>{html.escape(run['command'])}</code></p>")


def write_report(out_dir, summary: dict, design_report: dict, design_figures: list[str],
                 name: str = "report.html", run: dict | None = None) -> Path:
    """Write the page into ``out_dir`` (atomically); image paths are relative to it. ``run``
    (:func:`run_info`: version, date, command line) goes under the title; by default this
    process's."""
    path = Path(out_dir) / name
    atomic_write_text(path, render_report(summary, design_report, design_figures, run or run_info()))
    return path
