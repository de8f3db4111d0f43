"""Cameras a scan can capture from in-process, beside ``--capture-cmd``.

* :class:`OpenCVCamera`: OpenCV's ``VideoCapture`` (the ``camera`` extra): a live UVC/V4L2
  device (``0``, ``/dev/video0``), a GStreamer pipeline (any source holding ``!``) or an RTSP/HTTP
  URL (each grab takes the next frame).
* :class:`VideoFileCamera`: a video file played back frame by frame, read with PyAV (the
  ``video`` extra; ``video:FILE``, and ``opencv:FILE`` for a file with a video suffix, since
  OpenCV's file reader corrupted its heap on some uncompressed AVIs).
* :class:`SimulatedCamera`: the digital twin's camera. It renders each frame through the forward
  model (:mod:`hbis_torch.simulate`) at the phases the motors read back, so the whole bench path
  (scan, capture, assemble, reconstruct) runs on one machine against ``hbis motors simulate``.

Both are context managers with ``grab(index, phases_deg) -> frame`` ((H, W) or (H, W, 3) array)
and the attributes ``bit_depth`` and ``black_level`` (None when unknown).
:func:`camera_from_spec` builds one from a command-line string.
"""

from __future__ import annotations

from typing import Self

import numpy as np
import torch

from hbis_torch.errors import HbisInputError


class OpenCVCamera:
    """Frames from ``cv2.VideoCapture``.

    Parameters
    ----------
    source : str or int
        Device index (``0``), device path, GStreamer pipeline (holds ``!``), URL or video file.
    warmup : int
        Frames read and dropped after opening (auto-exposure settling, stale buffers).
    """

    bit_depth = None
    black_level = None

    def __init__(self, source, warmup: int = 0):
        self.source = int(source) if isinstance(source, str) and source.isdigit() else source
        self.warmup = int(warmup)
        self._capture = None

    def __enter__(self) -> Self:
        from hbis_torch.optional import import_cv2

        cv2 = import_cv2("--camera opencv:...")
        api = cv2.CAP_GSTREAMER if isinstance(self.source, str) and "!" in self.source else cv2.CAP_ANY
        self._capture = cv2.VideoCapture(self.source, api)
        if not self._capture.isOpened():
            self._capture.release()
            raise HbisInputError(f"camera {self.source!r}: OpenCV cannot open it (no such device, file or "
                                 "pipeline, or this OpenCV build lacks its backend)")
        for _ in range(self.warmup):
            self._capture.read()
        return self

    def __exit__(self, *exc) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None

    def grab(self, index: int, phases_deg) -> np.ndarray:
        """The next frame: (H, W) when gray (equal B, G, R), else (H, W, 3) RGB."""
        from hbis_torch.capture.frames import bgr_frames

        if self._capture is None:
            raise RuntimeError("the camera is not open (use it in a with block)")
        ok, frame = self._capture.read()
        if not ok or frame is None:
            raise RuntimeError(f"camera {self.source!r} returned no frame for frame {index}")
        return bgr_frames(frame[None])[0]


class VideoFileCamera:
    """Frames of a video file, read with PyAV (:func:`hbis_torch.capture.frames.read_video`: the
    headers and the decoding limit are checked first); each grab takes the next frame.

    Parameters
    ----------
    path : str or Path
        The video file (AVI, MP4, MKV, MOV, ...).
    warmup : int
        Frames skipped at the start.
    """

    bit_depth = None
    black_level = None

    def __init__(self, path, warmup: int = 0):
        self.path, self.warmup = path, int(warmup)
        self._frames = None
        self._next = 0

    def __enter__(self) -> Self:
        from hbis_torch.capture.frames import read_video

        self._frames, self._next = read_video(self.path), self.warmup
        return self

    def __exit__(self, *exc) -> None:
        self._frames = None

    def grab(self, index: int, phases_deg) -> np.ndarray:
        """The next frame: (H, W) grey or (H, W, 3) RGB."""
        if self._frames is None:
            raise RuntimeError("the camera is not open (use it in a with block)")
        if self._next >= len(self._frames):
            raise RuntimeError(f"video {self.path} has no frame left for frame {index}")
        self._next += 1
        return self._frames[self._next - 1]


class SimulatedCamera:
    """The twin's camera: each frame rendered through the forward model at the given phases.

    Parameters
    ----------
    scene : Scene or str
        Object-plane scene, or a built-in scene name / image path fitted to the ROI's view as
        ``hbis simulate`` fits it.
    system : FoveaSystem
    roi : (u0, v0, width, height)
        Pixels read out.
    h : int
        Resolution improvement factor of the scan (sets the forward model's grid, as for
        ``hbis simulate``).
    reference_phases_deg : (float, float)
        The scan's initial phases: the scene is centred on the reference frame's view.
    sensor : SensorModel
        Noise, quantisation, fill factor, defocus.
    seed : int
        Frame k's noise comes from seed and k (the same frame grabbed again is the same).
    oversample, margin_px : forward-model settings (``hbis simulate``'s defaults).
    """

    def __init__(self, scene, system, roi, h: int, reference_phases_deg, sensor=None, seed: int = 0,
                 oversample: int = 8, margin_px: float = 8.0):
        from hbis_torch.checks import check_h, check_phase_pair, check_roi
        from hbis_torch.simulate.scenes import Scene
        from hbis_torch.simulate.sensor import SensorModel
        from hbis_torch.simulate.stacks import scene_for_roi

        self.system, self.h = system, check_h(h)
        self.roi = check_roi(system.camera, roi)
        self.reference = check_phase_pair(reference_phases_deg)
        self.sensor = sensor if sensor is not None else SensorModel()
        self.seed, self.oversample, self.margin_px = int(seed), int(oversample), float(margin_px)
        if isinstance(scene, str):
            scene = scene_for_roi(scene, system, self.roi, self.h, self.seed, margin_px=self.margin_px,
                                  oversample=self.oversample)
        elif not isinstance(scene, Scene):
            raise HbisInputError(f"scene must be a Scene, a built-in scene name or an image path, got {type(scene).__name__}")
        self.scene = scene
        self.bit_depth = self.sensor.bit_depth
        self.black_level = self.sensor.black_level_dn if self.sensor.bit_depth is not None else None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        pass

    def render(self, phases_deg):
        """Noise-free irradiance (H, W) at ``phases_deg`` and the truth (h H, h W) at the reference."""
        from hbis_torch.simulate.forward import render_scan

        phases = torch.tensor([self.reference, tuple(float(p) for p in phases_deg)], dtype=torch.float64)
        rendered = render_scan(self.scene, self.system, phases, 0, self.h, self.roi, self.sensor,
                               oversample=self.oversample, margin_px=self.margin_px, return_positions=False)
        return rendered.irradiance[1], rendered.truth

    def grab(self, index: int, phases_deg) -> np.ndarray:
        """Frame ``index`` at the read-back ``phases_deg`` (phi1, phi2), in the sensor's dtype."""
        from hbis_torch.simulate.sensor import expose

        irradiance, _ = self.render(phases_deg)
        generator = torch.Generator().manual_seed(self.seed * 100003 + int(index))
        return expose(irradiance, self.sensor, generator)

    def truth(self) -> np.ndarray:
        """What an ideal pitch-p/h sensor sees at the reference phases, (h H, h W) float32."""
        return self.render(self.reference)[1].numpy()


def camera_from_spec(spec: str, system=None, roi=None, h: int | None = None, reference_phases_deg=None,
                     seed: int = 0, warmup: int = 0):
    """A camera from ``opencv:SOURCE`` or ``sim:SCENE`` (SCENE: a built-in name or an image file)."""
    from pathlib import Path

    from hbis_torch.capture.frames import is_video

    kind, _, rest = str(spec).partition(":")
    if kind == "video" and rest or (kind == "opencv" and is_video(rest) and Path(rest).is_file()):
        return VideoFileCamera(rest, warmup=warmup)
    if kind == "opencv" and rest:
        return OpenCVCamera(rest, warmup=warmup)
    if kind == "sim" and rest:
        return SimulatedCamera(rest, system, roi, h, reference_phases_deg, seed=seed)
    raise HbisInputError(f"--camera must be opencv:SOURCE (device index, device path, GStreamer pipeline or URL), "
                         f"video:FILE (a video file) or sim:SCENE (the digital twin), got {spec!r}")
