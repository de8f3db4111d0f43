"""The reconstruction methods' own options on the command line: one flag per option of the
registry (:class:`hbis_torch.reconstruct.registry.Option`), for ``hbis reconstruct`` and
``hbis validate``."""

from __future__ import annotations

from hbis_torch.errors import HbisInputError


def options_by_flag(methods) -> dict:
    """Every method option by flag: (the :class:`hbis_torch.reconstruct.registry.Option`, the
    names of the methods that take it)."""
    by_flag: dict = {}
    for name, method in methods.items():
        for option in method.options:
            by_flag.setdefault(option.flag, (option, []))[1].append(name)
    return by_flag


def add_method_options(parser, methods) -> None:
    """One flag per method option, its help prefixed by the methods that take it; unset flags
    leave no attribute (``SUPPRESS``), so that :func:`method_keywords` sees which were given."""
    import argparse

    group = parser.add_argument_group("options of one method")
    for flag, (option, takers) in options_by_flag(methods).items():
        group.add_argument(flag, dest=option.keyword, default=argparse.SUPPRESS,
                           help=f"{', '.join(takers)}: {option.help}", **option.argparse)


def method_keywords(args, method, methods) -> dict:
    """The method options given on the command line, as the run function's keywords; an option
    of another method is refused with one line, before any work."""
    for flag, (option, takers) in options_by_flag(methods).items():
        if hasattr(args, option.keyword) and option.keyword not in method.keywords:
            raise HbisInputError(f"{flag} is only for --method {' or '.join(takers)}; "
                                 f"the {method.name} method does not take it")
    return {option.keyword: getattr(args, option.keyword) for option in method.options
            if hasattr(args, option.keyword)}


def keywords_for_methods(args, names, methods) -> dict:
    """The method options given on the command line, per method of ``names`` that takes them
    (``hbis validate`` scores several methods at once); an option none of them takes is refused
    with one line, before any work."""
    chosen = [methods[n] for n in names if n in methods]
    for flag, (option, takers) in options_by_flag(methods).items():
        if hasattr(args, option.keyword) and not any(option.keyword in m.keywords for m in chosen):
            raise HbisInputError(f"{flag} is only for --method {' or '.join(takers)}, which is not among the "
                                 "methods scored")
    return {m.name: {o.keyword: getattr(args, o.keyword) for o in m.options if hasattr(args, o.keyword)}
            for m in chosen}
