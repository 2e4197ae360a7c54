"""The shared front of every ``python -m jaxcal.<tool>`` command line: help, usage and
exit codes (0 done, 2 bad arguments). Parsing ``key=value`` overrides and storing
configs is library work and lives in :mod:`jaxcal.settings`."""

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
