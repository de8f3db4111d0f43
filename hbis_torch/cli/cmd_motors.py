"""``hbis motors``: drive the prism motors through a GRBL 1.1 controller (or its simulator)."""

from __future__ import annotations

import contextlib
import json
import math
import shlex
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING

from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import atomic_write_text, check_distinct_paths, check_output_path
from hbis_torch.checks import bounded_float, bounded_int
from hbis_torch.cli.common import H_ARG, PHASE_DEG, add_system_args, system_from_args

if TYPE_CHECKING:  # the driver (pyserial) and the simulator are imported by the actions that use them
    from hbis_torch.hardware.grbl import GrblController

SUMMARY = "drive the prism motors through a GRBL 1.1 controller: status, home, goto, scan, simulate"


def _pair(text: str, what: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise HbisInputError(f"{what} must be two numbers separated by a comma, got {text!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise HbisInputError(f"{what} must be finite, got {text!r}")
    return a, b


def register(sub) -> None:
    from hbis_torch.hardware.simulator_args import add_simulator_args

    p = sub.add_parser(
        "motors",
        help=SUMMARY,
        description="Prism 1 on GRBL's X axis, prism 2 on Y, degrees as GRBL units ($100/$101 = steps "
        "per degree after the belt ratio). --port takes any pyserial URL: /dev/ttyUSB0, COM3, "
        "socket://host:port, spy:///dev/ttyUSB0?file=log.txt. Try it without hardware: run "
        "'hbis motors simulate' and pass the port it prints.",
    )
    p.add_argument("--port", help="pyserial URL of the controller")
    p.add_argument("--baud", type=bounded_int(300, 4_000_000), default=115200, help="baud rate (default 115200)")
    p.add_argument("--timeout-s", type=bounded_float(0.0, 3600.0, lo_open=True), default=2.0, help="deadline for each reply (default 2 s)")
    p.add_argument("--welcome-timeout-s", type=bounded_float(0.0, 3600.0, lo_open=True), default=5.0,
                   help="deadline for the welcome line after a reset (default 5 s)")
    p.add_argument("--phase-offset-deg", default="0,0", metavar="O1,O2",
                   help="prism phases at machine position zero (default 0,0)")
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION", parser_class=type(p))

    a = actions.add_parser("status", help="firmware, state, phases and step sizes")
    a.add_argument("--json", action="store_true", help="print one JSON object")
    a.set_defaults(func=run_status)

    a = actions.add_parser("home", help="run the homing cycle ($H; needs $22=1)")
    a.set_defaults(func=run_home)

    a = actions.add_parser("unlock", help="leave the Alarm state without homing ($X)")
    a.set_defaults(func=run_unlock)

    a = actions.add_parser("goto", help="turn the prisms to phases PHI1 PHI2 (deg), the short way")
    a.add_argument("phi1", type=PHASE_DEG, help="phase of prism 1 [deg]")
    a.add_argument("phi2", type=PHASE_DEG, help="phase of prism 2 [deg]")
    a.add_argument("--feed", type=bounded_float(0.0, 1e6, lo_open=True), help="feed [deg/min] (default: rapid, $110/$111)")
    a.set_defaults(func=run_goto)

    a = actions.add_parser(
        "scan", help="run a sub-pixel scan: print the predicted AE, then move/settle/capture each frame",
        description="Plan the h x h scan (as 'hbis scan'), print the alignment error predicted for "
        "the controller's step size, then take every frame: move, wait for Idle, settle, read the "
        "phases back, run --capture-cmd. A journal records the frames taken; rerunning the same "
        "command after a fault resumes at the first frame not taken.")
    a.add_argument("--h", type=H_ARG, required=True, help="resolution improvement factor h (h x h frames)")
    a.add_argument("--phases-deg", default="5,70", metavar="A,B",
                   help="initial phases (default 5,70); a negative one needs the = form: --phases-deg=-0.2,-70")
    a.add_argument("--method", choices=("exact", "paper"), default="exact", help="inverse solution (default exact)")
    a.add_argument("--journal", default="motors-scan-journal.json",
                   help="journal of frames taken, for resuming (default ./motors-scan-journal.json)")
    a.add_argument("--resume", action="store_true",
                   help="accept a journal that already records the whole scan (nothing is moved; --out is "
                   "written from it); a journal of an unfinished scan is always resumed")
    a.add_argument("--settle-s", type=bounded_float(0.0, 3600.0), default=0.2, help="pause after each move before capturing (default 0.2 s)")
    a.add_argument("--feed", type=bounded_float(0.0, 1e6, lo_open=True), help="feed [deg/min] (default: rapid)")
    a.add_argument("--capture-cmd", metavar="CMD",
                   help="command run for each frame; {index}, {phi1}, {phi2} are replaced by the frame "
                   "index and the read-back phases (deg)")
    a.add_argument("--capture-timeout-s", type=bounded_float(0.0, 86400.0, lo_open=True), default=60.0, help="deadline for --capture-cmd (default 60 s)")
    a.add_argument("--out", help="write the planned and read-back phases to this JSON file")
    c = a.add_argument_group("capture in-process and assemble the stack (docs/capture.md)")
    c.add_argument("--camera", metavar="SPEC",
                   help="grab each frame from a camera instead of --capture-cmd: opencv:SOURCE (OpenCV "
                   "VideoCapture: device index or path, GStreamer pipeline, URL; the 'camera' extra), "
                   "video:FILE (a video file played back with PyAV; the 'video' extra) or sim:SCENE (the digital twin's camera: a built-in scene or image file rendered "
                   "through the forward model at the read-back phases)")
    c.add_argument("--frames", metavar="PATTERN",
                   help="frame files with {index} (e.g. 'frames/f{index:03d}.tif'): where --camera writes "
                   "each frame, or where --capture-cmd does (needed by --stack)")
    c.add_argument("--stack", metavar="STACK.tif",
                   help="when the scan is done, assemble the --frames files into this hbis-stack/1 file")
    c.add_argument("--roi", metavar="U0,V0,W,H",
                   help="where the frames sit on the sensor (sim: the pixels rendered; default: a 256 x 256 "
                   "square at the centre for sim, the whole sensor otherwise)")
    c.add_argument("--bit-depth", type=int, help="significant bits of the frames (default: the camera's, or the dtype's)")
    c.add_argument("--seed", type=int, default=0, help="sim camera: seed of the scene and the noise (default 0)")
    a.add_argument("--dry-run", action="store_true", help="print the plan and predicted AE, move nothing")
    a.add_argument("--steps-per-deg", metavar="S1,S2",
                   help="steps per degree for --dry-run without a controller (default: read $100/$101)")
    add_system_args(a)
    a.set_defaults(func=run_scan_cmd)

    a = actions.add_parser("simulate", help="serve a simulated GRBL 1.1 controller on a pseudo-terminal")
    add_simulator_args(a)
    a.set_defaults(func=run_simulate)


def _controller(args) -> GrblController:
    from hbis_torch.hardware.grbl import GrblController
    from hbis_torch.hardware.timeouts import GrblTimeouts

    if not args.port:
        raise HbisInputError("--port is required: the controller's pyserial URL, e.g. /dev/ttyUSB0 "
                             "(or run 'hbis motors simulate' and use the port it prints)")
    timeouts = GrblTimeouts(welcome_s=args.welcome_timeout_s, reply_s=args.timeout_s)
    return GrblController(args.port, baudrate=args.baud, timeouts=timeouts,
                          phase_offset_deg=_pair(args.phase_offset_deg, "--phase-offset-deg"))


def run_status(args) -> int:
    with _controller(args).open() as grbl:
        report = grbl.status()
        phases = grbl.phases_deg()
        data = {"version": grbl.version, "state": report.state, "phases_deg": list(phases),
                "steps_per_deg": list(grbl.steps_per_deg), "step_deg": list(grbl.step_deg),
                "homing_enabled": grbl.homing_enabled, "messages": list(grbl.messages)}
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    print(f"GRBL {data['version']} at {args.port}: {data['state']}")
    print(f"  phases       prism 1 {phases[0]:.3f} deg, prism 2 {phases[1]:.3f} deg")
    print(f"  steps/deg    $100 = {data['steps_per_deg'][0]:g}, $101 = {data['steps_per_deg'][1]:g} "
          f"(one step = {data['step_deg'][0]:.4f} / {data['step_deg'][1]:.4f} deg)")
    print(f"  homing       {'enabled ($22=1)' if data['homing_enabled'] else 'disabled ($22=0)'}")
    for message in data["messages"]:
        print(f"  message      {message}")
    return 0


def run_home(args) -> int:
    with _controller(args).open() as grbl:
        grbl.home()
        phases = grbl.phases_deg()
    print(f"homed: prism 1 {phases[0]:.3f} deg, prism 2 {phases[1]:.3f} deg")
    return 0


def run_unlock(args) -> int:
    with _controller(args).open() as grbl:
        grbl.unlock()
        state = grbl.status().state
    print(f"unlocked ($X): state {state}; the phases may be wrong until the prisms are homed")
    return 0


def run_goto(args) -> int:
    with _controller(args).open() as grbl:
        phases = grbl.move_to(args.phi1, args.phi2, feed_deg_per_min=args.feed)
    print(f"at prism 1 {phases[0]:.3f} deg, prism 2 {phases[1]:.3f} deg")
    return 0


def _planner():
    try:
        import hbis_torch.scan as planner
    except ImportError as exc:
        raise HbisInputError(f"the scan planner (hbis_torch.scan) is not available in this build: {exc}") from None
    return planner


def _plan_and_predict(args, steps_per_deg, initial_deg):
    """Plan from ``initial_deg`` (already on the motor step grid) and print the predicted AE."""
    planner = _planner()
    system = system_from_args(args)
    plan = planner.plan_scan(system, args.h, initial_phases_deg=initial_deg, method=args.method)
    ae = planner.step_alignment_error(system, plan, steps_per_deg)
    frames = plan.phases_deg.shape[0]
    print(f"scan plan: h = {args.h}, {frames} frames from phases ({initial_deg[0]:.4f}, {initial_deg[1]:.4f}) "
          f"deg, {args.method} inverse, step SL = {plan.step_mm * 1e3:.3f} um on the object plane")
    print(f"motor steps: {1 / steps_per_deg[0]:.5f} deg (prism 1), {1 / steps_per_deg[1]:.5f} deg (prism 2)")
    shown = ", ".join(f"{k} = {v:.4f}" for k, v in ae.items() if k.startswith("ae_") and isinstance(v, float))
    print(f"predicted alignment error with these steps (fractions of SL): {shown}", flush=True)
    return plan, ae


def _snapped(requested, reachable):
    if any(abs(a - b) > 1e-6 for a, b in zip(requested, reachable)):
        print(f"initial phases moved to the motor step grid: ({requested[0]:g}, {requested[1]:g}) -> "
              f"({reachable[0]:.4f}, {reachable[1]:.4f}) deg")
    return reachable


def _capture_command(template: str, timeout_s: float):
    try:
        template.format(index=0, phi1="0", phi2="0")
    except (KeyError, IndexError, ValueError):
        raise HbisInputError("--capture-cmd may only use {index}, {phi1} and {phi2}; write other braces "
                             "as {{ and }}") from None
    if not (math.isfinite(timeout_s) and timeout_s > 0):
        raise HbisInputError(f"--capture-timeout-s must be a positive number, got {timeout_s!r}")

    def capture(index: int, phases: tuple[float, float]) -> None:
        command = template.format(index=index, phi1=f"{phases[0]:.4f}", phi2=f"{phases[1]:.4f}")
        done = subprocess.run(shlex.split(command), timeout=timeout_s, capture_output=True, text=True)
        if done.returncode != 0:
            tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or [""]
            raise RuntimeError(f"{command!r} exited with {done.returncode} {tail[0]}".rstrip())
    return capture


def run_scan_cmd(args) -> int:
    from hbis_torch.capture.cameras import camera_from_spec
    from hbis_torch.checks import MAX_PHASE_DEG
    from hbis_torch.hardware.grbl_protocol import nearest_step_phase
    from hbis_torch.hardware.scan_executor import ScanJournal, run_scan

    requested = _pair(args.phases_deg, "--phases-deg")
    if max(abs(v) for v in requested) > MAX_PHASE_DEG:
        raise HbisInputError(f"--phases-deg must lie within +-{MAX_PHASE_DEG:g} degrees, got {args.phases_deg!r}")
    if not args.dry_run:
        check_output_path(args.journal, "--journal")
        if args.out:
            check_output_path(args.out)
            check_distinct_paths({"--journal": args.journal}, {"--out": args.out})
    if args.dry_run and args.steps_per_deg:
        steps = _pair(args.steps_per_deg, "--steps-per-deg")
        if not (steps[0] > 0 and steps[1] > 0):
            raise HbisInputError(f"--steps-per-deg must be positive, got {args.steps_per_deg!r}")
        offsets = _pair(args.phase_offset_deg, "--phase-offset-deg")
        initial = tuple(nearest_step_phase(p, s, o) for p, s, o in zip(requested, steps, offsets))
        _plan_and_predict(args, steps, _snapped(requested, initial))
        return 0
    if args.steps_per_deg:
        raise HbisInputError("--steps-per-deg is only for --dry-run; a real scan reads $100/$101 from the controller")
    # Every check that needs no controller comes before the port is opened (and the controller reset).
    roi = _capture_checks(args)
    controller = _controller(args)
    _planner().plan_scan(system_from_args(args), args.h, initial_phases_deg=requested, method=args.method)
    capture = lambda index, phases: None  # noqa: E731 - moves and read-backs only
    if not args.dry_run:
        ScanJournal.read(args.journal)  # a corrupt one; whether it is this scan's needs the plan
        if args.camera:
            # the spec, scene and ROI; made again below around the phases the motors can reach
            camera_from_spec(args.camera, system_from_args(args), roi, args.h, requested, seed=args.seed)
        elif args.capture_cmd:
            capture = _capture_command(args.capture_cmd, args.capture_timeout_s)
    with controller.open() as grbl, contextlib.ExitStack() as stack:
        # Plan from phases the motors can reach, so the controller's rounding to whole steps is
        # the one the AE prediction models (steps counted from the initial phases).
        initial = _snapped(requested, grbl.nearest_reachable(*requested))
        plan, ae = _plan_and_predict(args, grbl.steps_per_deg, initial)
        if args.dry_run:
            return 0
        if args.camera:
            camera = camera_from_spec(args.camera, system_from_args(args), roi, args.h, initial, seed=args.seed)
            stack.enter_context(camera)
            capture = _camera_capture(camera, args.frames)

        def progress(record, total):
            print(f"frame {record.index} ({record.index + 1} of {total}): planned ({record.target_deg[0]:.4f}, "
                  f"{record.target_deg[1]:.4f}) read back ({record.phases_deg[0]:.4f}, "
                  f"{record.phases_deg[1]:.4f}) deg", flush=True)

        journal = ScanJournal.open(Path(args.journal), plan.phases_deg)
        if journal.complete and not args.resume:
            raise HbisInputError(f"the journal {args.journal} already records all {len(journal.targets)} frames of "
                                 "this scan, so there is nothing to take: pass --resume to accept it as it is, "
                                 "or give a new --journal")
        result = run_scan(grbl, plan.phases_deg, capture, journal=journal,
                          settle_s=args.settle_s, feed_deg_per_min=args.feed, on_frame=progress)
        steps = list(grbl.steps_per_deg)
    frames = result.phases_deg.shape[0]
    resumed = f" (resumed at frame {result.resumed_from})" if result.resumed_from else ""
    if result.resumed_from == frames:
        resumed = " (all already in the journal: none taken now)"
    print(f"scan done: {frames} frames{resumed}, {result.retries} retried after recoverable faults; "
          f"journal {args.journal}")
    if args.out:
        from hbis_torch.stack_io import system_meta

        data = {"format": "hbis-motor-phases/1", "h": args.h, "method": args.method, "steps_per_deg": steps,
                "initial_phases_deg": list(initial), "reference_index": int(plan.reference_index),
                "targets_deg": result.targets_deg.tolist(), "phases_deg": result.phases_deg.tolist(),
                "predicted_ae": {k: v for k, v in ae.items() if isinstance(v, (int, float))},
                "system": system_meta(system_from_args(args))}
        atomic_write_text(args.out, json.dumps(data, indent=1))
        print(f"wrote {args.out}")
    if args.stack:
        _assemble(args, plan, initial, result, roi, camera if args.camera else None)
    return 0


def _capture_checks(args):
    """Check the capture options before anything moves; return the ROI (or None)."""
    from hbis_torch.capture.frames import pattern_paths

    if args.camera and args.capture_cmd:
        raise HbisInputError("give --camera or --capture-cmd, not both")
    if (args.camera or args.stack) and not args.frames:
        raise HbisInputError("--camera and --stack need --frames PATTERN: the frame files, with {index}")
    if args.frames:
        pattern_paths(args.frames, 1)
        if "{index" not in args.frames:
            raise HbisInputError(f"--frames must hold {{index}} (one file per frame), got {args.frames!r}")
    if args.stack and not (args.camera or args.capture_cmd):
        raise HbisInputError("--stack needs frames: give --camera or a --capture-cmd that writes --frames")
    roi = None
    if args.roi:
        try:
            roi = tuple(int(t) for t in args.roi.split(","))
        except ValueError:
            roi = ()
        if len(roi) != 4:
            raise HbisInputError(f"--roi must be four integers U0,V0,WIDTH,HEIGHT, got {args.roi!r}")
    system = system_from_args(args)
    if args.camera and args.camera.startswith("sim:") and roi is None:
        from hbis_torch.cli.cmd_simulate import default_roi

        roi = default_roi(system.camera)
    if roi is not None:
        from hbis_torch.checks import check_roi

        roi = check_roi(system.camera, roi)
    return roi


def _camera_capture(camera, pattern: str):
    """capture(index, phases): grab a frame from ``camera`` and write it (atomically) as TIFF."""
    import tifffile

    from hbis_torch.io_utils import atomic_path

    def capture(index: int, phases: tuple[float, float]) -> None:
        frame = camera.grab(index, phases)
        path = Path(pattern.format(index=index))
        with atomic_path(path) as tmp:
            tifffile.imwrite(tmp, frame, photometric="rgb" if frame.ndim == 3 else "minisblack")
    return capture


def _assemble(args, plan, initial, result, roi, camera) -> None:
    """Assemble the scan's frame files into --stack (the checks of 'hbis assemble')."""
    from hbis_torch.capture import ScanPhases, assemble_stack, read_frames
    from hbis_torch.stack_io import system_meta, write_stack

    system = system_from_args(args)
    scan = ScanPhases(args.h, result.phases_deg.numpy(), result.targets_deg.numpy(), int(plan.reference_index),
                      tuple(initial), args.method, system_meta(system), args.out or "scan")
    frames, _ = read_frames([args.frames], count=scan.frames)
    bit_depth = args.bit_depth if args.bit_depth is not None else getattr(camera, "bit_depth", None)
    black = getattr(camera, "black_level", None)
    stack = assemble_stack(frames, scan, system, roi=roi, bit_depth=bit_depth, black_level=black)
    write_stack(args.stack, stack)
    print(f"wrote {args.stack}: {len(frames)} frames, h = {args.h}, roi {list(stack.roi)}")


def run_simulate(args) -> int:
    from hbis_torch.hardware.simulator import serve_until_done, simulator_from_args

    return serve_until_done(simulator_from_args(args))
