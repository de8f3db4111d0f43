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
