"""The shared front of every ``python -m jaxcal.<tool>`` command line: help, usage and
exit codes (0 done, 2 bad arguments), and the documented ``--flag value`` spellings as
``key=value`` tokens. Parsing ``key=value`` overrides and storing configs is library
work and lives in :mod:`jaxcal.settings`: every command line has that one grammar."""

from __future__ import annotations

import typing
from collections.abc import Sequence
from typing import Any


def parse_command_line(
    argv: Sequence[str] | None,
    parse: typing.Callable[[list[str]], Any],
    doc: str | None,
    usage: str,
) -> tuple[Any, int | None]:
    """The shared front of every ``python -m jaxcal.<tool>`` entry point.

    ``-h``/``--help``/``help`` prints ``doc`` and ``usage`` (exit code 0); a
    ``ValueError`` from ``parse`` is printed with the usage (exit code 2), so a typo
    fails before any heavy import.

    Returns:
        ``(parsed, None)`` to go on, or ``(None, exit_code)`` to stop.
    """
    import sys

    args = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("-h", "--help", "help") for a in args):
        print(doc or "")
        print(usage)
        return None, 0
    try:
        return parse(args), None
    except ValueError as err:
        print(f"error: {err}\n{usage}", file=sys.stderr)
        return None, 2


def flags_as_overrides(
    argv: Sequence[str],
    flags: typing.Mapping[str, str],
    switches: typing.Collection[str] = (),
) -> list[str]:
    """``argv`` with its documented ``--flag value`` / ``--flag=value`` spellings (and
    bare ``--switch`` booleans) as the ``key=value`` tokens of the one parser,
    :func:`jaxcal.settings.parse_overrides`; other tokens pass through.

    Args:
        argv: the command line's tokens.
        flags: ``{"--num-processes": "num_processes", ...}``, flag to config key.
        switches: the flags among ``flags`` that take no value (``--quick``).

    Raises:
        ValueError: an unknown flag (listing the known ones) or one without its
            value.
    """
    out: list[str] = []
    tokens = list(argv)
    while tokens:
        token = tokens.pop(0)
        if not token.startswith("--"):
            out.append(token)
            continue
        name, sep, value = token.partition("=")
        if name not in flags:
            raise ValueError(
                f"unknown flag {name!r}; the flags are {', '.join(flags)} (or "
                "key=value)"
            )
        if name in switches and not sep:
            value = "true"
        elif not sep:
            if not tokens or tokens[0].startswith("--"):
                raise ValueError(f"{name} needs a value: {name} VALUE")
            value = tokens.pop(0)
        out.append(f"{flags[name]}={value}")
    return out
