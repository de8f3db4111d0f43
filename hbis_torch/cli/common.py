"""Options shared by several subcommands: the Table 1 parameters of the system, and the
``type=`` helpers that check every number at the door (argparse answers a bad one in one line
with exit code 2, before any work)."""

from __future__ import annotations

import argparse

from hbis_torch.checks import MAX_H, MAX_PHASE_DEG, bounded_float, bounded_int
from hbis_torch.config import MAX_SENSOR_SIDE, Camera, Prisms, FoveaSystem


#: Ranges of the Table 1 flags: physics (n > 1, 0 < alpha < 90, F >= 0.5 in air) and what a
#: sensor can be (at most 65,536 pixels a side); generous elsewhere.
H_ARG = bounded_int(1, MAX_H)
SEED_ARG = bounded_int(0, 2**32 - 1)
PIXEL_PITCH_UM = bounded_float(0.0, 1000.0, lo_open=True)
SENSOR_SIDE = bounded_int(1, MAX_SENSOR_SIDE)
FOCAL_LENGTH_MM = bounded_float(0.0, 1e5, lo_open=True)
F_NUMBER = bounded_float(0.5, 1000.0)
WAVELENGTH_NM = bounded_float(100.0, 20000.0)
WEDGE_ANGLE_DEG = bounded_float(0.0, 90.0, lo_open=True, hi_open=True)
REFRACTIVE_INDEX = bounded_float(1.0, 5.0, lo_open=True)
OBJECT_DISTANCE_MM = bounded_float(0.0, 1e9, lo_open=True)
PHASE_DEG = bounded_float(-MAX_PHASE_DEG, MAX_PHASE_DEG)


def add_system_args(parser: argparse.ArgumentParser) -> None:
    """Add one flag per Table 1 parameter (defaults: the paper's prototype)."""
    cam, pr, sysd = Camera(), Prisms(), FoveaSystem()
    g = parser.add_argument_group("system (defaults: the paper's Table 1)")
    g.add_argument("--pixel-pitch-um", type=PIXEL_PITCH_UM, default=cam.pixel_pitch_um, help="pixel pitch p [um]")
    g.add_argument("--rows", type=SENSOR_SIDE, default=cam.rows, help="sensor rows M")
    g.add_argument("--cols", type=SENSOR_SIDE, default=cam.cols, help="sensor columns N")
    g.add_argument("--focal-length-mm", type=FOCAL_LENGTH_MM, default=cam.focal_length_mm, help="focal length f' [mm]")
    g.add_argument("--f-number", type=F_NUMBER, default=cam.f_number, help="F-number F")
    g.add_argument("--wavelength-nm", type=WAVELENGTH_NM, default=cam.wavelength_nm, help="wavelength [nm]")
    g.add_argument("--alpha-deg", type=WEDGE_ANGLE_DEG, default=pr.wedge_angle_deg, help="prism wedge angle a [deg]")
    g.add_argument("--n", type=REFRACTIVE_INDEX, default=pr.refractive_index, help="prism refractive index n")
    g.add_argument("--object-distance-mm", type=OBJECT_DISTANCE_MM, default=sysd.object_distance_mm,
                   help="object distance v [mm]")


def system_from_args(args: argparse.Namespace) -> FoveaSystem:
    """The FoveaSystem the flags describe (raises HbisInputError on bad values)."""
    camera = Camera(
        pixel_pitch_um=args.pixel_pitch_um,
        rows=args.rows,
        cols=args.cols,
        focal_length_mm=args.focal_length_mm,
        f_number=args.f_number,
        wavelength_nm=args.wavelength_nm,
    )
    prisms = Prisms(wedge_angle_deg=args.alpha_deg, refractive_index=args.n)
    return FoveaSystem(camera=camera, prisms=prisms, object_distance_mm=args.object_distance_mm)


def add_system_file_args(parser: argparse.ArgumentParser) -> None:
    """``--system FILE`` (JSON or TOML: camera, prisms, distance, lens) and ``--calibration FILE``
    (OpenCV's FileStorage output), beside the flags of :func:`add_system_args`."""
    g = parser.add_argument_group("system file and lens calibration")
    g.add_argument("--system", metavar="FILE",
                   help="camera, prisms, object distance and lens calibration in one JSON or TOML file "
                   "(instead of the flags above; docs/capture.md)")
    g.add_argument("--calibration", metavar="FILE",
                   help="the lens calibration OpenCV wrote (cv2.FileStorage YAML/XML/JSON: camera matrix "
                   "and distortion coefficients); FILE:M1 picks one camera of a stereo calibration; needs "
                   "the 'camera' extra")


_SYSTEM_FLAGS = ("pixel_pitch_um", "rows", "cols", "focal_length_mm", "f_number", "wavelength_nm",
                 "alpha_deg", "n", "object_distance_mm")


def system_for(args: argparse.Namespace, defaults: argparse.Namespace | None = None) -> FoveaSystem:
    """The system from ``--system`` (when given, the flags must stay at their defaults) or the
    flags, with ``--calibration``'s lens when given."""
    if getattr(args, "system", None):
        from hbis_torch.capture.system_file import load_system
        from hbis_torch.errors import HbisInputError

        ref = FoveaSystem()
        plain = {"pixel_pitch_um": ref.camera.pixel_pitch_um, "rows": ref.camera.rows, "cols": ref.camera.cols,
                 "focal_length_mm": ref.camera.focal_length_mm, "f_number": ref.camera.f_number,
                 "wavelength_nm": ref.camera.wavelength_nm, "alpha_deg": ref.prisms.wedge_angle_deg,
                 "n": ref.prisms.refractive_index, "object_distance_mm": ref.object_distance_mm}
        changed = [k for k in _SYSTEM_FLAGS if getattr(args, k, plain[k]) != plain[k]]
        if changed:
            raise HbisInputError(f"give the system either in --system or as flags, not both (--{changed[0].replace('_', '-')})")
        system = load_system(args.system)
    else:
        system = system_from_args(args)
    if getattr(args, "calibration", None):
        from hbis_torch.capture.lens import read_opencv_calibration
        from hbis_torch.capture.system_file import with_lens

        system = with_lens(system, read_opencv_calibration(args.calibration), args.calibration)
    return system


def tell(command: str, messages, about: str | None = None) -> None:
    """Show what a step said (its ``messages`` list) by the one verbosity rule of the CLI: a line
    that asks the user to act (:class:`hbis_torch.notices.UserAction`) as a warning, shown by
    default and marked ``warning:``; any other line only with ``-v``; nothing with ``-q``.

    Each line reads ``hbis COMMAND: [ABOUT: ][warning: ]TEXT`` on stderr (``about``: the stack
    or method the line is about, where a command runs several)."""
    import logging

    from hbis_torch.notices import asks_to_act

    log = logging.getLogger("hbis_torch.cli")
    where = f"hbis {command}: " + (f"{about}: " if about else "")
    for line in messages:
        if asks_to_act(line):
            log.warning("%swarning: %s", where, line, extra={"hbis_line": True})
        else:
            log.info("%s%s", where, line, extra={"hbis_line": True})


def add_overwrite_arg(parser: argparse.ArgumentParser) -> None:
    """``--overwrite``: the one rule for output files: nothing written is overwritten unless this
    flag is given. One output (``--out``, ``--truth``) that exists already is refused before any
    work; each file of ``--out-dir`` that exists already is skipped (an earlier run wrote it: a
    rerun finishes the rest, with or without ``--scheduler``)."""
    parser.add_argument("--overwrite", action="store_true",
                        help="replace output files that exist already (without it, --out and --truth are refused "
                        "before any work, and each file of --out-dir is skipped, so a rerun resumes)")
