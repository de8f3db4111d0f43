"""training/eval_matrix.py and its held-out matrix (hbis_torch.training.heldout): the stacks are
what their conditions say."""

import json

import numpy as np
import pytest

from hbis_torch.reconstruct.learned import noise_params_from_meta
from hbis_torch.provenance import read_provenance
from hbis_torch.training import heldout


@pytest.fixture(scope="module")
def em(load_script):
    return load_script("training/eval_matrix.py")


def condition(em, words):
    return next(c for c in heldout.CONDITIONS if words in c.name)


def test_captured_like_stacks_carry_no_noise_model_unless_asked(em):
    plain, _ = heldout.make_stack(condition(em, "reference frame 0"), "camera", 2, 16, seed=1)
    assert plain.reference_index == 0 and noise_params_from_meta(plain.meta) is None
    told, _ = heldout.make_stack(condition(em, "noise in the metadata"), "camera", 2, 16, seed=1)
    assert noise_params_from_meta(told.meta)[0] == pytest.approx(1 / 10_000)
    last, _ = heldout.make_stack(condition(em, "corner"), "camera", 2, 16, seed=1)
    assert last.reference_index == 3 and last.roi[:2] == (8, 8)


def test_the_unseen_forward_models_change_frames_and_truth_as_documented(em):
    sharp, sharp_truth = heldout.make_stack(condition(em, "no blur"), "camera", 2, 24, seed=1)
    blurred, blurred_truth = heldout.make_stack(condition(em, "Gaussian PSF"), "camera", 2, 24, seed=1)
    detail = lambda img: np.abs(np.diff(np.asarray(img, np.float64), axis=1)).mean()  # noqa: E731
    assert detail(blurred_truth) < 0.8 * detail(sharp_truth)  # the truth carries the lens's blur
    vignetted, truth = heldout.make_stack(condition(em, "vignetting"), "camera", 2, 24, seed=1)
    gain = heldout.vignetting(np.array([0.0, 11.5]), np.array([0.0, 11.5]), 24, 24)
    assert gain[0] == pytest.approx(0.7) and gain[1] == pytest.approx(1.0)
    assert vignetted.frames.dtype == sharp.frames.dtype and truth.shape == (48, 48)


def test_independent_rows_render_their_own_frames_and_truth_of_the_same_scan(em):
    """The [independent renderer] rows keep the simulator's stack's metadata (scan, roi, sensor)
    and replace its frames and truth by hbis_torch.training.independent_render's."""
    plain, plain_truth = heldout.make_stack(condition(em, "reference frame 0"), "camera", 2, 16, seed=1)
    other, other_truth = heldout.make_stack(condition(em, "F1.4, 10k e-, ref 0 [independent"), "camera", 2, 16, seed=1)
    assert other.meta == plain.meta and other.frames.dtype == plain.frames.dtype
    assert not np.array_equal(other.frames, plain.frames) and not np.array_equal(other_truth, plain_truth)
    # the same scene through the same optics: close, short of the noise
    assert np.abs(other_truth - plain_truth).mean() < 0.01


def test_cells_outside_the_training_domain_report_both_the_method_and_the_network(em, tmp_path, capsys):
    out = tmp_path / "cells.json"
    md = tmp_path / "cells.md"
    assert em.main(["--h", "2", "--photos", "camera", "--size", "24", "--out", str(out), "--md", str(md)]) == 0
    record = json.loads(out.read_text())
    assert record["provenance"]["command"].endswith(f"--out {out} --md {md}")  # where the cells came from
    assert read_provenance(md)["commit"] == record["provenance"]["commit"] and "| condition |" in md.read_text()
    cells = {c["condition"]: c for c in record["cells"]}
    outside = cells[condition(em, "outside ranges").name]
    inside = cells[condition(em, "reference frame 0").name]
    assert "lens cutoff" in outside["classical_returned"] and outside["delta_db"] == 0.0  # the classical image
    assert outside["extrapolated_delta_db"] != 0.0  # what the network would have given
    assert inside["classical_returned"] is None and "extrapolated_delta_db" not in inside
    printed = capsys.readouterr().out
    assert "+0.00*" in printed and "extrapolate=True" in printed
    assert em.main(["--h", "2", "--out", str(out)]) == 2  # never overwrites a result


def test_a_tier_runs_at_its_own_default_self_ensemble(em, tmp_path, capsys):
    # --tier best scores the best models as hbis reconstruct --model best runs them (2 symmetries)
    out = tmp_path / "best.json"
    assert em.main(["--h", "4", "--tier", "best", "--photos", "camera", "--size", "16", "--out", str(out)]) == 0
    assert {c["ensemble"] for c in json.loads(out.read_text())["cells"]} == {2}
    assert "self-ensemble of 2 at h = 4" in capsys.readouterr().out
