"""``hbis reconstruct STACK... --out-dir DIR``: many stacks in one process."""

import shutil

import numpy as np
import pytest
import tifffile

from hbis_torch.cli import main
from hbis_torch.cli.reconstruct_batch import expand_stacks
from hbis_torch.errors import HbisInputError


@pytest.fixture(scope="module")
def stacks(tmp_path_factory):
    from test_learned_cli import simulated_stack_file

    folder = tmp_path_factory.mktemp("stacks")
    first, _ = simulated_stack_file(folder, 2, size=16)
    paths = [first]
    for name in ("b", "c"):
        paths.append(folder / f"{name}.tif")
        shutil.copy(first, paths[-1])
    return paths


def test_out_dir_writes_every_stack_and_names_the_one_that_fails(stacks, tmp_path, capsys):
    broken = tmp_path / "broken.tif"
    broken.write_text("not a TIFF")
    out = tmp_path / "out"
    code = main(["reconstruct", *map(str, stacks), str(broken), "--out-dir", str(out), "--registration", "optics"])
    captured = capsys.readouterr()
    assert code == 2  # the worst stack's exit code: bad input
    written = sorted(p.name for p in out.iterdir() if p.name != ".lock")  # the run's lock stays, released
    assert written == sorted(f"{p.stem}.classical.tif" for p in stacks)
    assert "reconstructed 3 of 4 stacks" in captured.out and f"exit 2: {broken}" in captured.out
    assert [line for line in captured.err.splitlines() if str(broken) in line and "not" in line]
    single = tmp_path / "single.tif"  # the same image as a run with --out
    assert main(["reconstruct", str(stacks[1]), "--out", str(single), "--registration", "optics"]) == 0
    np.testing.assert_array_equal(tifffile.imread(single), tifffile.imread(out / f"{stacks[1].stem}.classical.tif"))


def test_existing_outputs_are_skipped_so_a_rerun_resumes(stacks, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    existing = out / f"{stacks[0].stem}.classical.tif"
    existing.write_bytes(b"keep me")  # what an earlier run wrote: never overwritten
    code = main(["reconstruct", *map(str, stacks), "--out-dir", str(out), "--registration", "optics"])
    printed = capsys.readouterr().out
    assert code == 0 and "reconstructed 2 of 3 stacks" in printed and "1 done before, skipped" in printed
    assert existing.read_bytes() == b"keep me"
    assert sorted(p.name for p in out.iterdir()) == sorted([".lock"] + [f"{p.stem}.classical.tif" for p in stacks])
    assert main(["reconstruct", *map(str, stacks), "--out-dir", str(out), "--overwrite", "--registration", "optics"]) == 0
    assert existing.read_bytes() != b"keep me" and "reconstructed 3 of 3 stacks" in capsys.readouterr().out
    odd = tmp_path / "odd"
    (odd / f"{stacks[0].stem}.classical.tif").mkdir(parents=True)  # an output --overwrite could not replace
    assert main(["reconstruct", str(stacks[0]), "--out-dir", str(odd), "--overwrite"]) == 2
    assert "not a regular file" in capsys.readouterr().err and sorted(p.name for p in odd.iterdir()) == [
        f"{stacks[0].stem}.classical.tif"]  # refused before any work


def test_glob_and_list_file(stacks, tmp_path):
    listing = tmp_path / "stacks.txt"
    listing.write_text(f"# two of them\n{stacks[0]}\n\n{stacks[1].name}\n")
    shutil.copy(stacks[1], tmp_path / stacks[1].name)  # relative lines are relative to the list's folder
    assert expand_stacks([f"@{listing}"]) == [stacks[0], tmp_path / stacks[1].name]
    assert expand_stacks([str(stacks[0].parent / "*.tif")]) == sorted(stacks)
    with pytest.raises(HbisInputError, match="no stack matches"):
        expand_stacks([str(tmp_path / "nothing*.tif")])
    with pytest.raises(HbisInputError, match="named twice"):
        expand_stacks([str(stacks[0]), str(stacks[0].parent / "*.tif")])


def test_out_takes_one_stack(stacks, tmp_path, capsys):
    assert main(["reconstruct", str(stacks[0]), str(stacks[1]), "--out", str(tmp_path / "x.tif")]) == 2
    assert "--out-dir" in capsys.readouterr().err
