"""The lens blur measured on a burst's own straight edges (hbis_torch/reconstruct/lens_blur.py)."""

import math

import numpy as np
import pytest
from scipy.special import ndtr

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.cli import main
from hbis_torch.reconstruct.burst import burst_samples
from hbis_torch.reconstruct.classical.burst import burst_sample_noise
from hbis_torch.reconstruct.lens_blur import (DOUBT_RAMP, FULL_TRUST, GROUP_WIDTH, LOOSE_WIDTH, MAX_TRUSTED,
                                              SCENE_MARGIN, LensEstimate, bound_to_undo, edge_profile,
                                              estimate_lens_sigma, sharpest_group, sigma_to_undo, stray_share)
from hbis_torch.reconstruct.registry import reconstruct
from hbis_torch.simulate.burst import random_motions, simulate_burst
from hbis_torch.training.burst_data import truth_raster


@pytest.mark.parametrize("theta, sigma, aperture", [(0.0, 0.3, 1.0), (0.4, 0.1, 1.0), (1.2, 0.6, 0.8)])
def test_the_edge_profile_is_the_step_through_the_pixel_and_the_lens(theta, sigma, aperture):
    """The closed form against a brute-force average of the blurred step over the pixel's area."""
    d = np.linspace(-2.5, 2.5, 41)
    q = (np.arange(400) + 0.5) / 400 - 0.5
    u, v = np.meshgrid(q * aperture, q * aperture)
    across = u * math.cos(theta) + v * math.sin(theta)  # each point's offset along the normal
    brute = np.array([ndtr((x + across) / sigma).mean() for x in d])
    np.testing.assert_allclose(edge_profile(d, theta, sigma, aperture), brute, atol=2e-4)


def _burst(scene: str, blur: float, size: int = 160, frames: int = 8, seed: int = 1):
    rng = np.random.default_rng(seed)
    truth = truth_raster(scene, 2, size, 10 + seed, 0.8)
    motions = random_motions(frames, (size, size), rng, max_shift=2.0, max_rotation_deg=0.5)
    burst = simulate_burst(truth, 2, motions, noise=0.01, seed=seed, blur_px=blur)
    stack, _ = assemble_burst(burst.frames, 2)
    return burst, stack


def _estimate(stack):
    frames, positions, _, weights = burst_samples(stack)
    noise = burst_sample_noise(frames, positions, weights)
    return estimate_lens_sigma(frames.numpy(), positions.numpy(), weights.numpy(), stack.reference_index, noise)


@pytest.mark.parametrize("blur", [0.0, 0.3, 0.6])
def test_a_known_lens_blur_is_recovered_from_the_burst(blur):
    _, stack = _burst("edges", blur)
    found = _estimate(stack)
    assert found.sharpest is not None and abs(found.sharpest - blur) < 0.08, (blur, found)


def test_a_burst_without_straight_edges_undoes_no_lens():
    _, stack = _burst("texture", 0.3, size=96)
    found = _estimate(stack)
    assert found.sharpest is None and found.sigma == 0, found
    assert "not measured" in found.describe() and "clean straight edges" in found.describe()


def test_the_lens_is_the_sharpest_edges_pile_up_not_their_spread():
    """One lens: the sharpest edges agree, a few stray fits below them; a soft scene: they spread."""
    rng = np.random.default_rng(0)
    lens = np.sort(np.concatenate([[0.12, 0.2], 0.3 + rng.normal(0, 0.01, 20), rng.uniform(0.35, 1.2, 30)]))
    sigma, members, agreement, below = sharpest_group(lens)
    assert abs(sigma - 0.3) < 0.01 and members >= 18 and agreement == 1 and below == 2
    spread = sharpest_group(np.sort(np.linspace(0.4, 1.0, 40)))  # evenly spread: no pile-up, a trace at most
    assert spread is None or spread[2] < 0.1, spread
    # more stray fits below the group than a few: a share of one lens at most, none with twice as many
    pile = 0.3 + rng.normal(0, 0.01, 20)
    four = sharpest_group(np.sort(np.concatenate([[0.1, 0.13, 0.16, 0.19], pile])))
    assert four is not None and four[3] == 4 and four[2] == pytest.approx(2 / 3), four
    assert sharpest_group(np.sort(np.concatenate([np.linspace(0.05, 0.2, 7), pile]))) is None


def test_a_loose_group_has_a_share_of_its_lens_undone():
    """Agreement 1 within GROUP_WIDTH, falling linearly to 0 at LOOSE_WIDTH times it: a group spread
    halfway between counts half."""
    width = GROUP_WIDTH[0] + GROUP_WIDTH[1] * 0.3
    loose = 0.3 + np.linspace(0, (1 + LOOSE_WIDTH) / 2 * width, 8)
    sigma, members, agreement, _ = sharpest_group(np.sort(np.concatenate([loose, [0.9, 1.0, 1.1]])))
    assert agreement == pytest.approx(0.5) and abs(sigma - np.median(loose)) < 1e-12
    assert sharpest_group(0.3 + np.linspace(0, 1.01 * LOOSE_WIDTH * width, 8)) is None


def test_stray_fits_below_the_lens_may_grow_with_the_edges():
    """Among 60 edges, 5 stray fits below a pile-up of 30 still leave it the lens (a tenth may stray)."""
    rng = np.random.default_rng(1)
    strays = [0.1, 0.14, 0.18, 0.22, 0.26]
    many = np.sort(np.concatenate([strays, 0.4 + rng.normal(0, 0.005, 30), rng.uniform(0.45, 1.2, 25)]))
    found = sharpest_group(many)
    assert found is not None and abs(found[0] - 0.4) < 0.01 and found[2] == 1, found
    # the same strays below a pile-up of 20 among 25 edges are more than the 3 always allowed: a
    # third of the weight is left (stray_share)
    few = np.sort(np.concatenate([strays, 0.4 + rng.normal(0, 0.005, 20)]))
    found = sharpest_group(few)
    assert found is not None and found[3] == 5 and found[2] == pytest.approx(1 / 3), found


def test_the_strays_share_falls_with_their_count_without_a_cliff():
    """One more accepted edge or one more stray changes the weight by a step, never from all to
    none: the held-out bursts of 50 and 51 edges with five strays once got 0 and 0.41 LR px."""
    rng = np.random.default_rng(2)
    pile, soft = 0.41 + rng.normal(0, 0.004, 25), rng.uniform(0.5, 1.2, 40)
    weights = {}
    for strays in range(4, 11):
        for accepted in (50, 51):
            sigmas = np.sort(np.concatenate([np.linspace(0.1, 0.31, strays), pile, soft]))[:accepted]
            found = sharpest_group(sigmas)
            weights[strays, accepted] = 0.0 if found is None else found[2]
            assert found is None or (found[3] >= strays - 1 and found[2] <= stray_share(found[3], accepted) + 1e-12)
            if strays < 9:  # (at 9, a group may still start on the highest stray, at a trace of weight)
                assert found[3] == strays and abs(found[0] - 0.41) < 0.01, found
                assert weights[strays, accepted] == pytest.approx(stray_share(strays, accepted))
    assert weights[5, 50] == weights[5, 51] == 1 and weights[10, 50] < 0.01
    assert all(abs(weights[k, 50] - weights[k, 51]) < 0.05 for k in range(4, 11))
    assert all(0 <= weights[k, 50] - weights[k + 1, 50] <= 0.21 for k in range(4, 10))


def test_soft_edges_have_a_share_of_their_blur_undone_falling_to_none():
    """Full below FULL_TRUST (less the scene's margin), nothing from MAX_TRUSTED on, continuous and
    never rising between: no two nearly equal bursts get answers a lens apart."""
    assert sigma_to_undo(0.3) == pytest.approx(math.sqrt(0.3**2 - SCENE_MARGIN**2))
    assert sigma_to_undo(FULL_TRUST) == pytest.approx(math.sqrt(FULL_TRUST**2 - SCENE_MARGIN**2))
    assert sigma_to_undo(MAX_TRUSTED) == 0 and sigma_to_undo(1.5) == 0
    grid = np.linspace(FULL_TRUST, MAX_TRUSTED, 301)
    undone = np.array([sigma_to_undo(float(s)) for s in grid])
    assert np.all(np.diff(undone) <= 1e-12) and np.max(np.abs(np.diff(undone))) < 0.01


def test_the_estimates_doubt_rises_from_full_trust_over_its_ramp():
    """0 while the sharpest edges are taken for the lens (or none agree), 1 once they lie a ramp
    above FULL_TRUST, linear and continuous between."""
    def doubt(sharpest):
        return LensEstimate(sharpest, 0.3, 10, 40, np.zeros(40), 60).doubt

    assert doubt(None) == 0 and doubt(0.3) == 0 and doubt(FULL_TRUST) == 0
    assert doubt(FULL_TRUST + DOUBT_RAMP / 2) == pytest.approx(0.5)
    assert doubt(FULL_TRUST + DOUBT_RAMP) == 1 and doubt(MAX_TRUSTED) == 1


def test_reconstruct_measures_the_lens_by_default_and_says_so():
    burst, stack = _burst("edges", 0.5)
    said: list[str] = []
    auto = reconstruct(stack, "classical", messages=said)
    none = reconstruct(stack, "classical", lens_sigma=0.0)
    assert any(line.startswith("lens blur: ") and "undoing sigma" in line for line in said), said
    truth = burst.truth

    def error(image):
        return float(np.mean((image - truth) ** 2))

    assert error(auto) < 0.8 * error(none)


@pytest.mark.parametrize("value, accepted", [("auto", True), ("0.3", True), ("nope", False), ("4", False)])
def test_psf_sigma_takes_auto_or_a_number(tmp_path, capsys, value, accepted):
    """A bad value is refused before the stack is looked for; a good one goes on to find it missing."""
    args = ["reconstruct", str(tmp_path / "no-such-stack.tif"), "--method", "classical", "--psf-sigma", value,
            "--out", str(tmp_path / "sr.tif")]
    try:
        code = main(args)
    except SystemExit as stop:
        code = stop.code
    err = capsys.readouterr().err
    assert code == 2
    assert ("no such file" in err) == accepted and ("--psf-sigma" in err) != accepted, err


@pytest.mark.parametrize("sharpest, sigma, agreement, said", [
    (0.3, 0.28, 1.0, "undoing sigma 0.28"),
    (0.3, 0.2, 0.7, "agree only loosely"),
    (0.6, 0.3, 1.0, "so soft that it may be the scene's own; undoing a share, sigma 0.30"),
    (0.05, 0.0, 1.0, "within the scene's own margin"),
    (0.85, 0.0, 1.0, "softer than any focused lens"),
])
def test_the_line_says_how_much_of_the_lens_is_undone_and_why(sharpest, sigma, agreement, said):
    from hbis_torch.reconstruct.lens_blur import LensEstimate

    line = LensEstimate(sharpest, sigma, 8, 40, np.linspace(0.1, 1, 40), 80, agreement).describe()
    assert line.startswith("lens blur: ") and said in line, line


def test_the_line_says_when_strays_cost_the_group_a_share():
    from hbis_torch.reconstruct.lens_blur import LensEstimate

    edges = np.linspace(0.1, 1, 50)
    line = LensEstimate(0.41, 0.8 * sigma_to_undo(0.41), 25, 50, edges, 80, 0.8, 6).describe()
    assert "above 6 sharper fits" in line and "undoing a share, sigma 0.32" in line, line
    assert "sharper fits" not in LensEstimate(0.41, sigma_to_undo(0.41), 25, 50, edges, 80, 1.0, 4).describe()


@pytest.mark.parametrize("bad", [["--scale", "1"], ["--frames", "1"], ["--blurs", "0.3", "-0.1"], ["--photos-size", "9x9"]])
def test_eval_lens_blur_refuses_bad_settings_before_any_work(tmp_path, capsys, load_script, bad):
    """One line and exit code 2, before a burst is rendered, and nothing written."""
    script = load_script("training/eval_lens_blur.py")
    out = tmp_path / "lens.json"
    with pytest.raises(SystemExit) as stop:
        script.main(["--out", str(out), *bad])
    assert stop.value.code == 2 and "error:" in capsys.readouterr().err
    assert not out.exists()


def test_the_structure_tensor_at_points_equals_the_whole_frames():
    """The edge search smooths the structure tensor only around the pixels it reads: it must
    equal the whole frame's smoothed tensor there, down to the bit, even a radius from the edge."""
    from scipy.ndimage import gaussian_filter

    from hbis_torch.reconstruct.lens_blur import _structure_at

    rng = np.random.default_rng(3)
    gy, gx = np.gradient(gaussian_filter(rng.random((40, 52)), 1.0))
    jxx, jyy, jxy = (gaussian_filter(a, 1.5) for a in (gx * gx, gy * gy, gx * gy))
    whole = np.sqrt((jxx - jyy) ** 2 + 4 * jxy * jxy) / (jxx + jyy)
    ys, xs = np.array([6, 6, 20, 33, 33]), np.array([6, 45, 25, 6, 45])
    coherence, angle = _structure_at(gx, gy, ys, xs)
    assert np.array_equal(coherence, whole[ys, xs])
    assert angle == [0.5 * math.atan2(2 * jxy[y, x], jxx[y, x] - jyy[y, x]) for y, x in zip(ys, xs)]


def test_the_noise_operator_in_pieces_is_the_whole_frames(monkeypatch):
    """The lens estimate's noise reads Immerkaer's operator a few rows at a time: the same values
    as over the whole frame, so the same median."""
    from hbis_torch.reconstruct import lens_blur
    from hbis_torch.sensor.noise import immerkaer

    frame = np.random.default_rng(4).random((23, 17), dtype=np.float32)
    whole = np.abs(immerkaer(frame.astype(np.float64))).reshape(-1)
    monkeypatch.setattr(lens_blur, "NOISE_PIECE_SAMPLES", 40)  # two rows a piece
    assert np.array_equal(lens_blur._immerkaer_magnitude(frame), whole)


def test_a_group_s_lost_weight_goes_to_the_sharper_fits_below_it():
    """Fits below a discounted group pull the sigma undone towards theirs, not towards nothing:
    never above the group's own, and nothing where no fit lies below."""
    from hbis_torch.reconstruct.lens_blur import sharpest_group, undone

    rng = np.random.default_rng(4)
    # photographs at their own scale: six edges near the lens (0.3), a pile-up softened by the scene
    sigmas = np.sort(np.concatenate([0.26 + rng.normal(0, 0.01, 6), 0.45 + rng.normal(0, 0.01, 12),
                                     rng.uniform(0.5, 0.8, 20)]))
    sharpest, _, agreement, below = sharpest_group(sigmas)
    assert agreement < 1 and below == 6
    sigma = undone(sigmas, sharpest, agreement, below)
    assert agreement * sigma_to_undo(sharpest) + 0.1 < sigma < sigma_to_undo(sharpest)
    assert sigma == pytest.approx(agreement * sigma_to_undo(sharpest)
                                  + (1 - agreement) * sigma_to_undo(float(np.median(sigmas[:6]))))
    # with no fit below, the rest goes to the sharpest edges' bound (never above the group's own)
    assert undone(sigmas, sharpest, agreement, 0) == pytest.approx(
        agreement * sigma_to_undo(sharpest) + (1 - agreement) * min(bound_to_undo(sigmas), sigma_to_undo(sharpest)))
    assert undone(sigmas, sharpest, 1.0, below) == pytest.approx(sigma_to_undo(sharpest))
    # a soft group's trust ramp caps what the fits below it may add
    assert undone(sigmas, 0.75, 0.5, below) == pytest.approx(sigma_to_undo(0.75))


@pytest.mark.parametrize("cluttered, expected", [(8, True), (3, False)])
def test_too_few_clean_edges_take_the_fits_beside_other_texture(monkeypatch, cluttered, expected):
    """Four edges pass the residual test and ``cluttered`` more only its looser bound (texture
    beside the edge): with 8 of those the lens is measured on all of them and the line says so;
    with 3 (7 in all) it is not measured."""
    import hbis_torch.reconstruct.lens_blur as lens_blur

    noise, contrast = 0.01, 40.0
    strict = lens_blur.MAX_RESIDUAL_NOISE + lens_blur.MAX_RESIDUAL_STEP * contrast
    loose = lens_blur.MAX_RESIDUAL_NOISE + lens_blur.CLUTTERED_RESIDUAL_STEP * contrast
    rng = np.random.default_rng(0)
    fits = [(0.3 + 0.005 * rng.standard_normal(), 0.01, contrast * noise, 0.5 * strict) for _ in range(4)]
    fits += [(0.3 + 0.005 * rng.standard_normal(), 0.01, contrast * noise, (strict + loose) / 2)
             for _ in range(cluttered)]
    fits += [(0.1, 0.01, contrast * noise, 1.1 * loose)] * 5  # beyond even the loose bound
    estimate = _estimate_from_fits(monkeypatch, fits, noise)
    assert estimate.cluttered is expected
    if expected:
        assert estimate.edges == 12 and estimate.sharpest == pytest.approx(0.3, abs=0.01)
        assert estimate.sigma == pytest.approx(sigma_to_undo(estimate.sharpest), rel=1e-6)
        assert "beside other texture" in estimate.describe()
    else:
        assert estimate.sharpest is None and estimate.sigma == 0 and estimate.edges == 4


def test_edges_that_do_not_agree_have_the_lens_bound_they_give_undone(monkeypatch):
    """Sharp edges spread with no group (a scene's own sharpening spreads them): the lens is at most
    the sharpest three's median, which is undone less the scene's margin; a soft scene's spread
    edges (from MAX_TRUSTED on) have nothing undone, and the line says which."""
    noise, contrast = 0.01, 40.0
    for spread, expected in ((np.linspace(0.2, 0.7, 30), sigma_to_undo(0.2 + 0.5 / 29)),
                             (np.linspace(0.85, 1.6, 30), 0.0)):
        assert sharpest_group(spread) is None
        estimate = _estimate_from_fits(monkeypatch, [(float(s), 0.01, contrast * noise, 1.0) for s in spread], noise)
        assert estimate.sharpest is None and estimate.sigma == pytest.approx(expected)
        line = estimate.describe()
        assert "do not agree" in line and f"at most {np.median(spread[:3]):.2f} LR px" in line
        assert ("none undone" in line) == (expected == 0)


def _estimate_from_fits(monkeypatch, fits: list, noise: float):
    """:func:`estimate_lens_sigma` of a burst whose edges' fits are ``fits`` (sigma, its error,
    c1, RMS residual in noise units), one edge point each."""
    import hbis_torch.reconstruct.lens_blur as lens_blur

    monkeypatch.setattr(lens_blur, "_edge_points", lambda reference, noise: [(20.0, 20.0, 0.0)] * len(fits))
    monkeypatch.setattr(lens_blur, "_samples", lambda *args: (np.zeros((1, 2)), np.zeros(1)))
    monkeypatch.setattr(lens_blur, "_fit_edges", lambda samples, thetas, noise, aperture: fits)
    return estimate_lens_sigma(np.zeros((2, 48, 48), np.float32), np.zeros((2, 48, 48, 2)),
                               np.ones((2, 48, 48)), 0, noise)
