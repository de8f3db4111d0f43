"""Every measured figure in the docs comes from a committed results file (tests/doc_figures.py)."""

import json

import pytest

import doc_figures as df
from hbis_torch.provenance import write_results

#: Pages not yet checked (docs/figures.md says why); every other page of README.md and docs/*.md is,
#: a new one included.
NOT_YET: set[str] = set()
ENFORCED = [str(p.relative_to(df.REPO)) for p in df.pages() if str(p.relative_to(df.REPO)) not in NOT_YET]


@pytest.mark.parametrize("page", ENFORCED)
def test_enforced_page_figures_match_their_results(page):
    problems = df.check_page(df.REPO / page)
    assert not problems, "\n".join(map(str, problems))


@pytest.fixture
def results(tmp_path, monkeypatch):
    monkeypatch.setattr(df, "REPO", tmp_path)
    write_results(tmp_path / "r.json", {"rows": [{"h": 4, "psnr": 31.504}, {"h": 7, "psnr": 30.0}],
                                        "t": {"fast": 2.0, "best": 2.6}, "s": {"a / b": 3.0}}, argv=[])
    write_results(tmp_path / "t.md", "| h | x |\n| 4 | 1.29 |\n", argv=[])
    (tmp_path / "bare.json").write_text(json.dumps({"a": 1.0}))
    return tmp_path


def _problems(root, text):
    page = root / "page.md"
    page.write_text(text)
    return [p.text for p in df.check_page(page)]


def test_marked_figures_pass(results):
    assert _problems(results, (
        "At h = 4 it gives 31.50 dB<!-- src: r.json: rows.[h=4].psnr -->, +1.50 dB over h = 7"
        "<!-- src: r.json: rows.[h=4].psnr - rows.[h=7].psnr -->, best/fast 1.3x<!-- src: r.json: t.best / t.fast -->"
        " and 1.29x<!-- src: t.md -->; a 2 s<!-- setting --> timeout; +1.0 dB<!-- src: r.json: s.\"a / b\" - t.best + 0.6 -->.\n"
        "```\n99 dB in a code block\n```\n`7 s` in a span\n"
        "<!-- src-table: t.md -->\n| h | speed |\n|---|---|\n| 4 | 1.29x |\n"
        "\n<!-- src-table: r.json -->\n| h | PSNR |\n|---|---|\n| 4 | 31.50 dB |\n")) == []


@pytest.mark.parametrize("text, expected", [
    ("31.6 dB<!-- src: r.json: rows.[h=4].psnr -->\n", "31.6 but"),  # differs from its file
    ("It takes 3.2 s.\n", "no source marker"),  # no source
    ("+0.35 better\n", "no source marker"),  # a signed decimal is a figure
    ("1.30x<!-- src: t.md -->\n", "1.30 is not in t.md"),
    ("1.30x and 31.50 dB<!-- src: t.md r.json -->\n", "1.30 is not in t.md r.json"),
    ("1.0 dB<!-- src: bare.json: a -->\n", "records no provenance"),
    ("1.0 dB<!-- src: gone.json: a -->\n", "does not exist"),
    ("1.0 dB<!-- src: r.json: rows.[h=5].psnr -->\n", "0 elements match"),
    ("<!-- src-table: t.md -->\n| 4 | 1.31x |\n", "1.31 is not in t.md"),
    ("<!-- src-table: r.json -->\n| 31.6 dB |\n", "31.6 is not in r.json"),
])
def test_wrong_or_unmarked_figures_fail(results, text, expected):
    problems = _problems(results, text)
    assert len(problems) == 1 and expected in problems[0], problems


def test_dimensions_and_exponents_are_not_figures(results):
    assert _problems(results, "A 3 x 3 array of 960 x 1280 sensors, K R K^-1.\n") == []


def test_no_docs_page_over_500_lines():
    # a page a user reads through; history goes to dated notes (docs/notes/)
    long = {str(p.relative_to(df.REPO)): n for p in df.pages()
            if (n := len(p.read_text().splitlines())) > 500}
    assert not long, long
