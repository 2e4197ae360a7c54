"""The shared front of every ``python -m jaxcal.<tool>`` command line: help, usage and
exit codes (0 done, 2 bad arguments), the closest valid key suggested for a misspelt
one, and the documented ``--flag value`` spellings as ``key=value`` tokens. Parsing
``key=value`` overrides and storing configs is library work and lives in
:mod:`jaxcal.settings`: every command line has that one grammar."""

from __future__ import annotations

import dataclasses
import difflib
import re
import sys
import typing
from collections.abc import Sequence
from typing import Any

from jaxcal.settings import UnknownKeyError, parse_overrides

# ``key=`` and ``--flag`` spellings of a usage line: keys a command line takes beyond
# its config's fields (train's ``outputs=``, ``test_units=``), offered as suggestions.
_USAGE_KEY = re.compile(
    r"(?<![\w.<|-])([A-Za-z_][\w.]*)=(?!value)|(?<![\w-])(--[\w-]+)"
)


def parse_command_line(
    argv: Sequence[str] | None,
    parse: typing.Callable[[list[str]], Any],
    doc: str | None,
    usage: str,
) -> tuple[Any, int | None]:
    """The shared front of every ``python -m jaxcal.<tool>`` entry point.

    ``-h``/``--help``/``help`` prints ``doc`` and ``usage`` (exit code 0); a
    ``ValueError`` from ``parse`` is printed with the usage (exit code 2), so a typo
    fails before any heavy import. A misspelt key (an :class:`UnknownKeyError`
    anywhere in the error's chain) close to a valid one gets one line, the error
    with ``(did you mean 'seed'?)``: the message already lists the valid keys.

    Returns:
        ``(parsed, None)`` to go on, or ``(None, exit_code)`` to stop.
    """
    args = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("-h", "--help", "help") for a in args):
        print(doc or "")
        print(usage)
        return None, 0
    try:
        return parse(args), None
    except ValueError as err:
        message = with_closest_key(err, usage)
        if "did you mean" in message:
            print(f"error: {message}", file=sys.stderr)
        else:
            print(f"error: {message}\n{usage}", file=sys.stderr)
        return None, 2


def with_closest_key(err: ValueError, usage: str = "") -> str:
    """The message of ``err``, with ``(did you mean 'KEY'?)`` after the unknown key
    when a valid key is close (:func:`difflib.get_close_matches`).

    The key and the valid keys come from the :class:`UnknownKeyError` in the chain of
    ``err`` (a wrapper that adds to the message keeps it as its context), plus the
    ``key=`` and ``--flag`` spellings of ``usage``. A message that already suggests
    one (``jaxcal.fleet``'s method options) is left as it is.
    """
    message = str(err)
    cause: BaseException | None = err
    while cause is not None and not isinstance(cause, UnknownKeyError):
        cause = cause.__cause__ or cause.__context__
    if cause is None or "did you mean" in message:
        return message
    spelled = [a or b for a, b in _USAGE_KEY.findall(usage)]
    candidates = [k for k in dict.fromkeys([*cause.valid, *spelled]) if k != cause.key]
    close = difflib.get_close_matches(cause.key, candidates, n=1)
    if not close:
        return message
    said = repr(cause.key)
    hint = f"{said} (did you mean {close[0]!r}?)"
    return message.replace(said, hint, 1) if said in message else f"{hint}: {message}"


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
            raise UnknownKeyError(
                f"unknown flag {name!r}; the flags are {', '.join(flags)} (or "
                "key=value)",
                key=name,
                valid=list(flags),
            )
        if name in switches and not sep:
            value = "true"
        elif not sep:
            if not tokens or tokens[0].startswith("--"):
                raise ValueError(f"{name} needs a value: {name} VALUE")
            value = tokens.pop(0)
        out.append(f"{flags[name]}={value}")
    return out


@dataclasses.dataclass(frozen=True)
class ClusterArgs:
    """The ``jax.distributed`` settings of a command line (``key=value`` or the
    documented flags, :data:`CLUSTER_FLAGS`); ``None``: from the environment
    (:func:`jaxcal.fleet.distributed.process_settings`)."""

    coordinator: str | None = None  # HOST:PORT of process 0
    num_processes: int | None = None
    process_id: int | None = None
    local_devices: int | None = None  # CPU devices of this process

    def resolve(self) -> dict:
        """The keyword arguments of :func:`jaxcal.fleet.distributed.initialize`:
        ``coordinator``, ``num_processes``, ``process_id`` (each from its flag,
        else its ``JAXCAL_*`` variable), ``local_device_count``.

        Raises:
            ValueError: naming the bad setting and the expected form.
        """
        # light --help: every command line imports this module (the cluster's code
        # loads when asked)
        from jaxcal.fleet.distributed import process_settings

        coordinator, num_processes, process_id = process_settings(
            self.coordinator, self.num_processes, self.process_id
        )
        return {
            "coordinator": coordinator,
            "num_processes": num_processes,
            "process_id": process_id,
            "local_device_count": self.local_devices,
        }


CLUSTER_FLAGS = {
    "--coordinator": "coordinator",
    "--num-processes": "num_processes",
    "--process-id": "process_id",
    "--local-devices": "local_devices",
}
CLUSTER_USAGE = (
    "[--coordinator HOST:PORT --num-processes N --process-id I] [--local-devices K]"
)


def split_cluster_args(argv: Sequence[str]) -> tuple[list[str], ClusterArgs]:
    """A command line's cluster settings (the flags of :data:`CLUSTER_FLAGS`, or their
    ``key=value`` form) apart from its other ``key=value`` tokens.

    Returns:
        ``(other tokens, settings)``; :meth:`ClusterArgs.resolve` completes the
        settings from the environment.

    Raises:
        ValueError: an unknown flag, a flag without its value or a bad value.
    """
    tokens = flags_as_overrides(argv, CLUSTER_FLAGS)
    keys = set(CLUSTER_FLAGS.values())
    ours = [t for t in tokens if t.partition("=")[0].strip() in keys]
    rest = [t for t in tokens if t.partition("=")[0].strip() not in keys]
    return rest, parse_overrides(ours, ClusterArgs())
