"""Options shared by several subcommands: the Table 1 parameters of the system."""

from __future__ import annotations

import argparse

from hbis_torch.config import Camera, Prisms, FoveaSystem


def add_system_args(parser: argparse.ArgumentParser) -> None:
    """Add one flag per Table 1 parameter (defaults: the paper's prototype)."""
    cam, pr, sysd = Camera(), Prisms(), FoveaSystem()
    g = parser.add_argument_group("system (defaults: the paper's Table 1)")
    g.add_argument("--pixel-pitch-um", type=float, default=cam.pixel_pitch_um, help="pixel pitch p [um]")
    g.add_argument("--rows", type=int, default=cam.rows, help="sensor rows M")
    g.add_argument("--cols", type=int, default=cam.cols, help="sensor columns N")
    g.add_argument("--focal-length-mm", type=float, default=cam.focal_length_mm, help="focal length f' [mm]")
    g.add_argument("--f-number", type=float, default=cam.f_number, help="F-number F")
    g.add_argument("--wavelength-nm", type=float, default=cam.wavelength_nm, help="wavelength [nm]")
    g.add_argument("--alpha-deg", type=float, default=pr.wedge_angle_deg, help="prism wedge angle a [deg]")
    g.add_argument("--n", type=float, default=pr.refractive_index, help="prism refractive index n")
    g.add_argument("--object-distance-mm", type=float, default=sysd.object_distance_mm,
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
                   "and distortion coefficients); needs the 'camera' extra")


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
