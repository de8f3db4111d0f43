"""The exact Risley tracer: closed forms, physical invariants, precision and bad input."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hbis_torch import Camera, HbisInputError, Prisms, FoveaSystem
from hbis_torch.optics import (
    axis_deviation,
    deviation_azimuth,
    exit_directions,
    land_on_plane,
    landing_map,
    landing_map_interpolated,
    pixel_rays,
    refract,
    risley_normals,
    sensor_position,
    trace_back,
    trace_faces,
    trace_risley,
)

angles = st.floats(-720.0, 720.0, allow_nan=False)
field = st.floats(-0.35, 0.35, allow_nan=False)  # ray slopes up to ~19 deg


def unit(x, y):
    r = torch.tensor([x, y, 1.0], dtype=torch.float64)
    return r / r.norm()


def test_single_prism_at_normal_incidence_deviates_by_closed_form():
    for a_deg, n in [(1.0, 1.5), (4.0, 1.5), (10.0, 1.7), (20.0, 2.0)]:
        prisms = Prisms(a_deg, n)
        flat, n12, _, _ = risley_normals(0.0, 0.0, prisms)
        out = trace_faces(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), [flat, n12], [1.0, n, 1.0])
        phi, _ = deviation_azimuth(out.directions)
        a = math.radians(a_deg)
        assert float(phi) == pytest.approx(math.degrees(math.asin(n * math.sin(a)) - a), abs=1e-10)


def test_aligned_pair_deviates_4_008_deg_toward_the_phase():
    phi, theta = axis_deviation(0.0, 0.0)
    assert float(phi) == pytest.approx(4.008, abs=5e-4)
    assert float(theta) == pytest.approx(0.0, abs=1e-9)
    # opposed prisms leave only a small residual deviation with this face layout
    phi_c, _ = axis_deviation(0.0, 180.0)
    assert 0 < float(phi_c) < 0.1


@settings(max_examples=60, deadline=None)
@given(phase=angles)
def test_aligned_azimuth_turns_with_the_phase(phase):
    phi, theta = axis_deviation(phase, phase)
    assert float(phi) == pytest.approx(4.008162, abs=1e-5)
    turn = (float(theta) - phase + 180.0) % 360.0 - 180.0
    assert turn == pytest.approx(0.0, abs=1e-8)


@settings(max_examples=60, deadline=None)
@given(x=field, y=field, p1=angles, p2=angles)
def test_exit_vectors_are_unit_and_trace_back_returns_the_ray(x, y, p1, p2):
    ray = unit(x, y)
    out = trace_risley(ray, p1, p2)
    assert bool(out.valid)
    assert float(out.directions.norm()) == pytest.approx(1.0, abs=1e-14)
    back = trace_back(out.directions, p1, p2).directions
    assert torch.allclose(back, ray, atol=1e-13)


@settings(max_examples=60, deadline=None)
@given(x=field, y=field, p1=angles, p2=angles)
def test_reversed_system_returns_the_ray(x, y, p1, p2):
    """The independent face-by-face tracer, run backwards, undoes the forward trace."""
    prisms = Prisms()
    n = prisms.refractive_index
    ray = unit(x, y)
    normals = risley_normals(p1, p2, prisms)
    forward = trace_faces(ray, normals, [1.0, n, 1.0, n, 1.0]).directions
    assert torch.allclose(forward, trace_risley(ray, p1, p2).directions, atol=1e-14)
    backward = trace_faces(-forward, normals[::-1], [1.0, n, 1.0, n, 1.0]).directions
    assert torch.allclose(-backward, ray, atol=1e-13)


@settings(max_examples=60, deadline=None)
@given(x=field, y=field, nx=st.floats(-0.5, 0.5), ny=st.floats(-0.5, 0.5), eta=st.floats(0.5, 1.0))
def test_n_sin_theta_is_conserved_at_a_face(x, y, nx, ny, eta):
    ray, normal = unit(x, y), unit(nx, ny)
    out, tir = refract(ray, normal, eta)
    assert not bool(tir)
    sin_i = torch.linalg.cross(ray, normal).norm()
    sin_t = torch.linalg.cross(out, normal).norm()
    assert float(eta * sin_i) == pytest.approx(float(sin_t), abs=1e-13)
    # the transmitted ray stays in the plane of incidence
    assert float(torch.dot(out, torch.linalg.cross(ray, normal))) == pytest.approx(0.0, abs=1e-13)


def test_total_internal_reflection_is_masked_never_nan():
    prisms = Prisms(40.0, 2.0)
    rays = pixel_rays(Camera(rows=4, cols=6))
    out = trace_risley(rays, 0.0, 0.0, prisms)
    assert not bool(out.valid.all())
    assert torch.isfinite(out.directions).all()
    with pytest.raises(HbisInputError, match="totally internally reflected"):
        exit_directions(rays, 0.0, 0.0, prisms)


def test_broadcasting_over_phases_and_rays():
    rays = pixel_rays(Camera(rows=3, cols=5))
    phases = torch.tensor([0.0, 45.0, 90.0], dtype=torch.float64)
    batch = exit_directions(rays, phases[:, None, None], 10.0)
    assert batch.shape == (3, 3, 5, 3)
    for i, p in enumerate(phases):
        assert torch.allclose(batch[i], exit_directions(rays, float(p), 10.0))


def test_float32_landing_map_within_1e_3_pixel_of_float64():
    """float32 is enough for simulation (error ~3e-4 object-plane pixel); analysis uses float64."""
    system = FoveaSystem()
    roi = (0, 0, 1280, 960)
    m64 = landing_map(system, 5.0, 70.0, roi)
    m32 = landing_map(system, 5.0, 70.0, roi, dtype=torch.float32)
    assert m32.dtype == torch.float32
    err = float((m32.double() - m64).abs().max()) / system.object_pixel_mm
    assert err < 1e-3


def test_interpolated_landing_maps_match_the_exact_trace():
    system = FoveaSystem()
    p1 = torch.tensor([5.0, 5.3, 5.6], dtype=torch.float64)
    p2 = torch.tensor([70.0, 69.8, 70.4], dtype=torch.float64)
    exact = landing_map(system, p1, p2)
    fast = landing_map_interpolated(system, p1, p2)
    assert fast.shape == exact.shape == (3, 960, 1280, 2)
    assert float((fast - exact).abs().max()) / system.object_pixel_mm < 1e-3
    roi = (1000, 700, 200, 180)  # a corner ROI uses its own geometry
    assert torch.allclose(landing_map_interpolated(system, p1, p2, roi), exact[:, 700:880, 1000:1200],
                          atol=1e-3 * system.object_pixel_mm)


def test_sensor_position_inverts_the_landing_map():
    system = FoveaSystem()
    roi = (1100, 800, 40, 30)
    points = landing_map(system, 33.0, 250.0, roi)
    uv = sensor_position(system, points, 33.0, 250.0)
    v, u = torch.meshgrid(torch.arange(800.0, 830.0), torch.arange(1100.0, 1140.0), indexing="ij")
    assert torch.allclose(uv, torch.stack((u, v), -1).double(), atol=1e-9)


def test_fast_kernel_matches_eager():
    rays = pixel_rays(Camera(rows=8, cols=10))
    a = trace_risley(rays, 12.0, 200.0).directions
    b = trace_risley(rays, 12.0, 200.0, fast=True).directions
    assert torch.allclose(a, b, atol=1e-14)


@pytest.mark.parametrize(
    "make",
    [
        lambda: Prisms(4.0, 1.0),
        lambda: Prisms(4.0, 0.8),
        lambda: Prisms(0.0, 1.5),
        lambda: Prisms(-1.0, 1.5),
        lambda: Prisms(90.0, 1.5),
        lambda: Prisms(float("nan"), 1.5),
        lambda: Prisms(4.0, float("inf")),
        lambda: Camera(rows=0),
        lambda: Camera(cols=0),
        lambda: Camera(pixel_pitch_um=float("nan")),
        lambda: FoveaSystem(object_distance_mm=0.0),
        lambda: trace_risley(torch.empty(0, 3, dtype=torch.float64), 0.0, 0.0),
        lambda: trace_risley(torch.ones(4, 2, dtype=torch.float64), 0.0, 0.0),
        lambda: trace_risley(torch.tensor([0.0, float("nan"), 1.0]), 0.0, 0.0),
        lambda: trace_risley(torch.tensor([0.0, 0.0, 1.0]), float("nan"), 0.0),
        lambda: trace_risley(torch.tensor([0.0, 0.0, -1.0]), 0.0, 0.0),
        lambda: landing_map(FoveaSystem(), 0.0, 0.0, roi=(0, 0, 0, 10)),
        lambda: landing_map(FoveaSystem(), 0.0, 0.0, roi=(1200, 0, 100, 10)),
        lambda: land_on_plane(torch.tensor([[0.0, 0.0, 1.0]]), -5.0),
    ],
)
def test_bad_input_gets_a_clear_error(make):
    with pytest.raises(HbisInputError):
        make()


def test_not_a_knot_basis_is_scipys_cubic_spline():
    import numpy as np
    from scipy.interpolate import CubicSpline

    from hbis_torch.optics.cubic_spline import not_a_knot_basis

    rng = np.random.default_rng(3)
    for knots in (np.linspace(0, 959, 11), np.linspace(0, 1, 4), np.sort(rng.random(7)) * 10, np.array([0.0, 2, 5])):
        at = np.linspace(knots[0] - 1, knots[-1] + 1, 257)  # extrapolation included
        np.testing.assert_allclose(not_a_knot_basis(knots, at), CubicSpline(knots, np.eye(len(knots)))(at),
                                   rtol=0, atol=1e-12)
