"""Check that every measured figure in the docs comes from a committed results file.

A doc author marks each figure with an invisible HTML comment naming its source (the rules are in
docs/figures.md):

* ``+0.50 dB<!-- src: benchmarks/results/x.json: key.path -->`` (JSON; several keys, comma
  separated, for the last numbers of the span; a key may be ``a - b``, ``a / b``, ...);
* ``1.29x<!-- src: benchmarks/results/x.md -->`` (text: the figure appears in the file; several
  files, space separated: in one of them);
* ``<!-- src-table: benchmarks/results/x.md -->`` on the line above a table;
* ``2 s<!-- setting -->`` for a number that is an input, not a result;
* ``> 80 %<!-- paper -->`` for a figure quoted from the paper the project reproduces.

Run ``python tests/doc_figures.py FILE...`` to list the problems of some pages.
"""

from __future__ import annotations

import ast
import json
import operator
import re
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

MARKER = re.compile(r"<!--\s*(src|setting|paper|src-table)\b:?\s*(.*?)\s*-->")
NUMBER = re.compile(r"(?<![\w.])([+\u2212-]?)(\d+(?:,\d{3})*(?:\.\d+)?(?:e[+-]?\d+)?)(?![\w.]*\d)")
UNIT = re.compile(r"\s?(dB|(?:x|\u00d7)(?!\s?\d)|s|ms|\u00b5s|us|min|%|times|fps|kB|MB|GB|KiB|MiB|GiB)(?![\w])")
CODE_SPAN = re.compile(r"`[^`]*`")
LINK_TARGET = re.compile(r"\]\([^)]*\)")
DATED_NOTE = re.compile(r"\d{4}-\d{2}(-\d{2})?-[\w-]+\.md$")
_OPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv}


@dataclass
class Problem:
    path: str
    line: int
    text: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.text}"


def _blank(text: str, pattern: re.Pattern) -> str:
    """``text`` with each match of ``pattern`` replaced by spaces (positions kept)."""
    return pattern.sub(lambda m: " " * len(m.group(0)), text)


def numbers(text: str) -> list[tuple[int, str, str, bool]]:
    """(position, sign, digits, is_figure) of each number in ``text`` (code spans, link targets
    and markers already blanked by the caller)."""
    out = []
    for m in NUMBER.finditer(text):
        sign, digits = m.group(1), m.group(2)
        # A unit makes a figure; so does a sign on a decimal (+0.35), not on an integer (K^-1).
        is_figure = (bool(sign) and "." in digits) or bool(UNIT.match(text, m.end()))
        out.append((m.start(), sign, digits, is_figure))
    return out


def _value(sign: str, digits: str) -> float:
    v = float(digits.replace(",", ""))
    return -v if sign in ("-", "\u2212") else v


def _tolerance(digits: str) -> float:
    """Half a unit of the last digit shown (``5.9e-05``: 5e-07), plus rounding slack."""
    mantissa, _, exponent = digits.partition("e")
    decimals = len(mantissa.split(".")[1]) if "." in mantissa else 0
    return 0.5 * 10 ** (int(exponent or 0) - decimals) * (1 + 1e-9) + 1e-12


def _part(node, part: str):
    if part.startswith("[") and part.endswith("]"):
        want = dict(kv.split("=", 1) for kv in part[1:-1].split(","))
        if not isinstance(node, list):
            raise KeyError(f"{part}: not a list")
        hits = [e for e in node if isinstance(e, dict) and all(str(e.get(k)) == v for k, v in want.items())]
        if len(hits) != 1:
            raise KeyError(f"{part}: {len(hits)} elements match")
        return hits[0]
    if isinstance(node, list):
        return node[int(part)]
    if isinstance(node, dict):
        if part in node:
            return node[part]
        raise KeyError(part)
    raise KeyError(f"{part}: not a container")


def lookup(data, path: str):
    """The value at a key path such as ``results.[method=learned,h=7].psnr`` (dots between parts;
    a part in double quotes may hold dots, spaces and operators: ``summary."rgb / classical"``)."""
    parts = re.findall(r'"[^"]*"|\[[^\]]*\]|[^.\[\]"]+', path)
    node = data
    for part in parts:
        node = _part(node, part[1:-1] if part.startswith('"') else part)
    return node


def evaluate(data, expr: str) -> float:
    """A key path, or arithmetic (``+ - * /`` with spaces around) of key paths and numbers."""
    names = {}
    quoted = re.findall(r'"[^"]*"', expr)  # a quoted key part may hold " / " or " - "
    for i, q in enumerate(quoted):
        expr = expr.replace(q, f"\0{i}\0", 1)
    tokens = [re.sub(r"\0(\d+)\0", lambda m: quoted[int(m.group(1))], t)
              for t in re.split(r"\s+([-+*/])\s+", expr.strip())]
    code = []
    for i, token in enumerate(tokens):
        if i % 2:
            code.append(token)
            continue
        try:
            code.append(repr(float(token)))
        except ValueError:
            key = f"_v{len(names)}"
            names[key] = float(lookup(data, token))
            code.append(key)
    code = " ".join(code)

    def ev(node):
        if isinstance(node, ast.Expression):
            return ev(node.body)
        if isinstance(node, ast.BinOp) and type(node.op) in _OPS:
            return _OPS[type(node.op)](ev(node.left), ev(node.right))
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return -ev(node.operand)
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)):
            return float(node.value)
        if isinstance(node, ast.Name) and node.id in names:
            return names[node.id]
        raise ValueError(f"cannot evaluate {expr!r}")

    return ev(ast.parse(code, mode="eval"))


class Sources:
    """Results files read once each, and whether they record provenance."""

    def __init__(self):
        self.cache = {}

    def get(self, rel: str):
        if rel not in self.cache:
            from hbis_torch.provenance import read_provenance

            path = REPO / rel
            if not path.is_file():
                self.cache[rel] = (None, None, f"{rel} does not exist")
            else:
                text = path.read_text(errors="replace")
                data = json.loads(text) if path.suffix == ".json" else None
                prov = read_provenance(path)
                self.cache[rel] = (text, data, None if prov else f"{rel} records no provenance")
        return self.cache[rel]

    def holds(self, digits: str, names) -> bool:
        """Whether one of the files ``names`` holds the figure: as written in a text file, or
        as some number rounded to it in a JSON one."""
        for name in names:
            text, data, _ = self.get(name)
            if text is not None and (_in_json(digits, data) if data is not None else _in_text(digits, text)):
                return True
        return False


def _in_text(digits: str, text: str) -> bool:
    return re.search(r"(?<![\d.])" + re.escape(digits) + r"(?![\d])", text) is not None


def _json_numbers(data) -> list[float]:
    if isinstance(data, dict):
        return [v for x in data.values() for v in _json_numbers(x)]
    if isinstance(data, list):
        return [v for x in data for v in _json_numbers(x)]
    if isinstance(data, (int, float)) and not isinstance(data, bool):
        return [abs(float(data))]
    return []


def _in_json(digits: str, data) -> bool:
    """Whether some number of a JSON results file, rounded as ``digits`` shows, is ``digits``
    (a table copied from a JSON file: weaker than a key per figure, so kept for tables)."""
    shown, tol = _value("", digits), _tolerance(digits)
    return any(abs(v - shown) <= tol for v in _json_numbers(data))


def check_page(path: Path, sources: Sources | None = None) -> list[Problem]:
    """Every problem with the figures of one markdown page."""
    sources = sources or Sources()
    rel = str(path.resolve().relative_to(REPO)) if path.resolve().is_relative_to(REPO) else str(path)
    problems: list[Problem] = []
    from hbis_torch.provenance import read_provenance

    if read_provenance(path) is not None:
        return []  # a page a benchmark writes (docs/speed-vs-error.md): it is its own results file
    in_code = False
    table_source = None  # results file of the table being read, if any
    for lineno, raw in enumerate(path.read_text().splitlines(), 1):
        if raw.lstrip().startswith("```"):
            in_code = not in_code
            continue
        if in_code:
            continue
        m = re.fullmatch(r"\s*<!--\s*src-table:\s*(.+?)\s*-->\s*", raw)
        if m:
            table_source = m.group(1)
            for name in table_source.split():
                err = sources.get(name)[2]
                if err:
                    problems.append(Problem(rel, lineno, err))
            continue
        is_table = raw.lstrip().startswith("|")
        if not is_table:
            table_source = None
        if raw.lstrip().startswith("#"):
            continue
        line = _blank(_blank(raw, CODE_SPAN), LINK_TARGET)
        if is_table and table_source:
            if re.fullmatch(r"[\s|:-]*", line):
                continue
            for _, _, digits, _ in numbers(_blank(line, MARKER)):
                if not sources.holds(digits, table_source.split()):
                    problems.append(Problem(rel, lineno, f"{digits} is not in {table_source}"))
            continue
        start = 0
        covered: set[int] = set()
        for marker in MARKER.finditer(line):
            span = _blank(line[:marker.start()], MARKER)
            nums = [n for n in numbers(span) if n[0] >= start]
            kind, arg = marker.group(1), marker.group(2)
            start = marker.end()
            if kind in ("setting", "paper"):
                covered.update(n[0] for n in nums)
                continue
            if kind != "src" or not arg:
                problems.append(Problem(rel, lineno, f"malformed marker {marker.group(0)}"))
                continue
            file, _, keys = arg.partition(":")
            file = file.strip()
            errors = [e for e in (sources.get(name)[2] for name in file.split()) if e]
            if errors:
                problems.extend(Problem(rel, lineno, e) for e in errors)
                covered.update(n[0] for n in nums)
                continue
            text, data, _ = sources.get(file.split()[0])
            if keys.strip():
                if data is None:
                    problems.append(Problem(rel, lineno, f"keys given for {file}, which is not JSON"))
                    continue
                exprs = [k for k in keys.split(",") if k.strip()]
                exprs = _rejoin_selectors(exprs)
                # The keys name the last figures of the span (the last numbers where too few
                # carry a unit or sign: "37.9 measured").
                figures = [n for n in nums if n[3]]
                pool = figures if len(figures) >= len(exprs) else nums
                if len(exprs) > len(pool):
                    problems.append(Problem(rel, lineno, f"{len(exprs)} keys but {len(pool)} numbers before {marker.group(0)}"))
                    continue
                for (pos, sign, digits, _), expr in zip(pool[len(pool) - len(exprs):], exprs):
                    covered.add(pos)
                    try:
                        value = evaluate(data, expr)
                    except (KeyError, IndexError, ValueError, TypeError, ZeroDivisionError) as exc:
                        problems.append(Problem(rel, lineno, f"{file}: {expr.strip()}: {exc}"))
                        continue
                    shown = _value(sign, digits)
                    if not sign:  # an unsigned figure may quote a magnitude ("lost 0.30 dB")
                        value = abs(value) if shown >= 0 else value
                    if abs(value - shown) > _tolerance(digits):
                        problems.append(Problem(rel, lineno, f"{sign}{digits} but {file}: {expr.strip()} = {value:.6g}"))
            else:
                targets = [n for n in nums if n[3]] or nums[-1:]
                for pos, _, digits, _ in targets:
                    covered.add(pos)
                    if not sources.holds(digits, file.split()):
                        problems.append(Problem(rel, lineno, f"{digits} is not in {file}"))
        bare = _blank(line, MARKER)
        for pos, sign, digits, is_figure in numbers(bare):
            if is_figure and pos not in covered:
                problems.append(Problem(rel, lineno, f"{sign}{digits}{UNIT.match(bare, pos + len(sign) + len(digits)).group(0) if UNIT.match(bare, pos + len(sign) + len(digits)) else ''}: no source marker"))
    return problems


def _rejoin_selectors(parts: list[str]) -> list[str]:
    """Comma-split keys glued back where the comma sat inside ``[k=v,k2=v2]`` or a quoted part."""
    out: list[str] = []
    for part in parts:
        if out and (out[-1].count("[") > out[-1].count("]") or out[-1].count('"') % 2):
            out[-1] += "," + part
        else:
            out.append(part)
    return out


def pages() -> list[Path]:
    """README.md and every docs page outside dated notes."""
    return [REPO / "README.md"] + sorted(p for p in (REPO / "docs").glob("*.md"))


def main(argv=None) -> int:
    files = [Path(a) for a in (sys.argv[1:] if argv is None else argv)] or pages()
    sources = Sources()
    problems = [p for f in files for p in check_page(f, sources)]
    for p in problems:
        print(p)
    print(f"{len(problems)} problems in {len(files)} pages", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    raise SystemExit(main())
