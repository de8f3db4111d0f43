"""What ``hbis validate`` reads from its ``--method`` values and writes as its JSON report, shared by
the command (:mod:`hbis_torch.cli.cmd_validate`) and its many-stack jobs (:mod:`hbis_torch.cli.jobs`)."""

from __future__ import annotations

from hbis_torch.errors import HbisInputError


def method_names(given) -> list[str]:
    """Method names from repeated and comma-separated ``--method`` values (None: the defaults)."""
    from hbis_torch.validate.cross import DEFAULT_METHODS, resolve_methods

    if not given:
        return list(DEFAULT_METHODS)
    names = [n.strip() for value in given for n in value.split(",")]
    if any(not n for n in names):
        raise HbisInputError(f"--method has an empty name in {','.join(given)!r}")
    return resolve_methods(names)


def json_report(result, name: str, kind: str) -> dict:
    """The object ``--json`` prints (and ``--out-dir`` writes per stack): the stack's file name,
    its kind and the scores; a burst's factor under ``scale`` (hbis assemble --burst --scale S)."""
    report = result.to_dict()
    if kind == "burst":
        report = {("scale" if k == "h" else k): v for k, v in report.items()}
    return {"stack": name, "kind": kind, **report}
