"""Command-line plumbing shared by the scripts: options built from typed dataclasses.

Every option is a dataclass field with a ``help`` in its metadata, so the
dataclass is the one source of truth. Errors are one line on stderr and exit
code 2, never a traceback.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import Any, NoReturn

_TYPES = {"int": int, "float": float, "str": str, "bool": bool}


def fail(message: str, code: int = 2) -> NoReturn:
    """Print one line on stderr and exit (2 = bad input)."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(code)


class Parser(argparse.ArgumentParser):
    """argparse whose errors are one line on stderr, exit code 2."""

    def error(self, message: str) -> NoReturn:
        fail(f"{message} (see --help)")


def option_name(field_name: str) -> str:
    return "--" + field_name.replace("_", "-")


def add_options(parser: argparse.ArgumentParser, config_class: type, title: str, present: set[str] = frozenset()) -> list[str]:
    """Add one option per dataclass field; unset options stay absent from the namespace.

    Fields named in ``present`` already have an option (another config shares
    the name): they are listed in the result but not added twice.
    """
    group = parser.add_argument_group(title)
    names = []
    for field in dataclasses.fields(config_class):
        if field.name in present:
            names.append(field.name)
            continue
        kind = _TYPES[field.type if isinstance(field.type, str) else field.type.__name__]
        help_text = f"{field.metadata.get('help', '')} (default: {field.default})"
        common = dict(dest=field.name, help=help_text, default=argparse.SUPPRESS)
        if kind is bool:
            group.add_argument(option_name(field.name), action=argparse.BooleanOptionalAction, **common)
        else:
            group.add_argument(option_name(field.name), type=kind, choices=field.metadata.get("choices"),
                               metavar=field.name.upper(), **common)
        names.append(field.name)
    return names


def parse_config(config_class: type, argv: list[str], description: str, title: str):
    """Parse ``argv`` into ``config_class`` for a script whose options are that one dataclass.

    Unknown options, bad types and the dataclass's own validation errors all
    end as one line on stderr with exit code 2.
    """
    from stablebptt.errors import InputError
    parser = Parser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(parser, config_class, title)
    try:
        return build(config_class, vars(parser.parse_args(argv)))
    except InputError as error:
        fail(str(error))


def build(config_class: type, values: dict[str, Any]):
    """The dataclass from the given values (unknown keys ignored); validation errors propagate."""
    known = {f.name for f in dataclasses.fields(config_class)}
    return config_class(**{k: v for k, v in values.items() if k in known})
