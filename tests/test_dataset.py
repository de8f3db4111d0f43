"""The on-the-fly training dataset and the validation set on disk."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from hbis_torch.errors import HbisInputError
from hbis_torch.simulate.dataset import DatasetConfig, SameHBatchSampler, SyntheticStacks
from hbis_torch.stack_io import read_image, read_stack

SMALL = DatasetConfig(length=50, crop=(24, 20), seed=3)


def test_items_have_the_documented_shapes_and_ranges():
    ds = SyntheticStacks(SMALL)
    item = ds[0]
    h = int(item["h"])
    frames = h * h
    assert item["frames"].shape == (frames, 20, 24) and item["frames"].dtype == torch.float32
    assert item["positions"].shape == (frames, 20, 24, 2) and item["true_positions"].shape == (frames, 20, 24, 2)
    assert item["truth"].shape == (h * 20, h * 24)
    assert 0 <= int(item["reference_index"]) < frames
    assert float(item["frames"].min()) >= 0 and float(item["frames"].max()) <= 1
    assert float(item["truth"].min()) >= 0 and float(item["truth"].max()) <= 1
    ref = int(item["reference_index"])
    grid = torch.stack(torch.meshgrid(torch.arange(24.0), torch.arange(20.0), indexing="xy"), -1)
    assert float((item["positions"][ref] - grid).abs().max()) < 1e-5  # the reference defines the grid


def test_items_are_deterministic_and_differ_between_indices():
    a, b = SyntheticStacks(SMALL), SyntheticStacks(SMALL)
    for i in (0, 7):
        x, y = a[i], b[i]
        assert all(torch.equal(x[k], y[k]) for k in x)
    assert not torch.equal(a[1]["truth"], a[2]["truth"]) or not torch.equal(a[1]["roi"], a[2]["roi"])
    other = SyntheticStacks(DatasetConfig(length=50, crop=(24, 20), seed=4))
    assert not torch.equal(a[0]["frames"], other[0]["frames"])


def test_rois_cover_corners_and_edges_and_h_comes_from_the_range():
    cfg = DatasetConfig(length=400, crop=(64, 64), h_choices=(2, 3, 4), seed=0)
    ds = SyntheticStacks(cfg)
    draws = [ds.draw(i) for i in range(400)]
    rois = np.array([d.roi for d in draws])
    cam = cfg.system.camera
    at_left, at_right = rois[:, 0] == 0, rois[:, 0] == cam.cols - 64
    at_top, at_bottom = rois[:, 1] == 0, rois[:, 1] == cam.rows - 64
    corners = (at_left | at_right) & (at_top | at_bottom)
    assert corners.sum() >= 10 and (at_left | at_right).sum() >= 50
    assert np.all(rois[:, 0] >= 0) and np.all(rois[:, 0] + 64 <= cam.cols)
    assert len({d.h for d in draws}) == 3 and all(ds.h_of(i) == draws[i].h for i in range(400))
    assert len({d.scene for d in draws}) >= 15  # procedural patterns and photographs
    full_wells = [d.sensor.full_well_e for d in draws]
    assert min(full_wells) < 2000 and max(full_wells) > 20000  # noise levels vary


def test_measured_and_true_positions_differ_by_the_phase_error():
    cfg = DatasetConfig(length=10, crop=(16, 16), phase_error_deg=(0.002, 0.002), seed=1)
    item = SyntheticStacks(cfg)[0]
    diff = (item["positions"] - item["true_positions"]).abs()
    assert float(diff[int(item["reference_index"])].max()) < 1e-6
    assert 1e-3 < float(diff.max()) < 0.5  # 0.002 deg of phase is a few hundredths of a pixel
    quiet = SyntheticStacks(DatasetConfig(length=10, crop=(16, 16), phase_error_deg=(0.0, 0.0)))[0]
    assert torch.equal(quiet["positions"], quiet["true_positions"])


def test_noise_free_item_is_consistent_with_its_truth():
    """Huge well, no read noise, fill factor 1, fine quantisation: the reference frame is the
    truth pooled over h x h blocks (the grid convention, docs/data.md)."""
    cfg = DatasetConfig(length=5, crop=(16, 16), full_well_log=(1e9, 1e9), read_noise=(0.0, 0.0),
                        fill_factor=(1.0, 1.0), bit_depths=(16,), black_level=(0.0, 0.0),
                        phase_error_deg=(0.0, 0.0), seed=2)
    item = SyntheticStacks(cfg)[0]
    h, ref = int(item["h"]), int(item["reference_index"])
    pooled = torch.nn.functional.avg_pool2d(item["truth"][None, None], h)[0, 0]
    assert float((pooled - item["frames"][ref]).abs().max()) < 3e-4


def test_same_h_batches_stack_in_a_dataloader():
    cfg = DatasetConfig(length=12, crop=(16, 16), h_choices=(2, 3), seed=5)
    ds = SyntheticStacks(cfg)
    sampler = SameHBatchSampler(ds, batch_size=3, seed=1)
    loader = DataLoader(ds, batch_sampler=sampler, num_workers=2)
    seen = []
    for batch in loader:
        h = int(batch["h"][0])
        assert torch.all(batch["h"] == h)
        assert batch["frames"].shape[1:] == (h * h, 16, 16) and batch["truth"].shape[1:] == (16 * h, 16 * h)
        seen.extend(batch["roi"][:, 0].tolist())
    assert len(seen) == 12
    first = [list(b) for b in sampler]
    sampler.set_epoch(1)
    assert first != [list(b) for b in sampler]  # reshuffled per epoch


def test_bad_configs_are_rejected():
    with pytest.raises(HbisInputError, match="crop"):
        DatasetConfig(crop=(2000, 10))
    with pytest.raises(HbisInputError, match="unknown scene"):
        DatasetConfig(scenes=("nope",))
    with pytest.raises(HbisInputError, match="h_choices"):
        DatasetConfig(h_choices=(0,))
    with pytest.raises(IndexError):
        SyntheticStacks(SMALL)[50]


def test_validation_set_is_written_resumed_and_readable(tmp_path):
    from hbis_torch.simulate.validation import write_validation_set

    cfg = DatasetConfig(length=3, crop=(16, 12), seed=9)
    index = write_validation_set(tmp_path, cfg, progress=False)
    assert len(index["items"]) == 3
    listed = json.loads((tmp_path / "index.json").read_text())
    assert listed == index and listed["config"]["seed"] == 9
    entry = listed["items"][1]
    stack = read_stack(tmp_path / entry["stack"])
    truth, meta = read_image(tmp_path / entry["truth"])
    item = SyntheticStacks(cfg)[1]
    assert torch.allclose(stack.to_float(), item["frames"])
    assert np.array_equal(truth, item["truth"].numpy())
    assert meta["h"] == stack.h and tuple(meta["roi"]) == stack.roi
    assert stack.meta["simulation"]["index"] == 1
    before = (tmp_path / entry["stack"]).stat().st_mtime_ns
    write_validation_set(tmp_path, cfg, progress=False)  # resumes: nothing to redo
    assert (tmp_path / entry["stack"]).stat().st_mtime_ns == before
    (tmp_path / entry["truth"]).unlink()
    write_validation_set(tmp_path, cfg, progress=False)
    assert (tmp_path / entry["truth"]).exists()
    with pytest.raises(HbisInputError, match="different configuration"):
        write_validation_set(tmp_path, DatasetConfig(length=3, crop=(16, 12), seed=10), progress=False)
