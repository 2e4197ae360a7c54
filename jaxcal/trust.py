"""Consent to run code from outside the installed jaxcal (``docs/trust.md``).

A run folder, an ``extended_model.json`` or a data file is data: what it says never
makes jaxcal import a module, run a ``.py`` or call a function on its own say-so.
Code outside the installed package runs only with the user's consent, which is one
of:

* the user named the code: ``model=path/to/file.py:attr`` on a command line, or
  ``jaxcal.models.load("path/to/file.py:attr")`` (or ``"package.module:attr"``) in
  Python. :func:`consent` records it for the process, as the sha256 of the file's
  bytes and the attribute: a run's copy of the same bytes, or an extension's base
  of the same bytes, then loads without asking again;
* ``trust_code=True`` in Python, ``trust_code=true`` on the command lines: the user
  trusts the code the run or the spec brings.

Anything else is refused with an :class:`UntrustedCodeError` naming the file and
how to consent (:func:`require_consent`). A host-only leaf: it imports nothing of
jaxcal.
"""

from __future__ import annotations

import hashlib

HOW_TO_CONSENT = (
    "if you trust it, pass trust_code=True (Python: jaxcal.deploy.load_run, "
    "StreamingCalibrator, jaxcal.models.load) or trust_code=true (jaxcal.evaluate, "
    "jaxcal.fleet), "
    "or name the same model yourself in this process (jaxcal.models.load("
    "'path/to/file.py:attr' or 'package.module:attr'), model= on a command line)"
)

_CONSENTED: set[tuple[str, str]] = set()  # (sha256 of the code's bytes, its name)


class UntrustedCodeError(ValueError):
    """Loading would run code outside the installed jaxcal that the user did not
    consent to (a ``ValueError``: the command lines exit 2 with its one line)."""


def sha256(content: bytes) -> str:
    return hashlib.sha256(content).hexdigest()


def consent(content: bytes, name: str) -> None:
    """Record that the user named the code ``content`` (a file's bytes) and its
    attribute ``name`` (``attr`` of a file, ``module:attr`` of a module)."""
    _CONSENTED.add((sha256(content), name))


def has_consent(content: bytes, name: str) -> bool:
    """Whether the user named these bytes and attribute in this process."""
    return (sha256(content), name) in _CONSENTED


def require_consent(content: bytes, name: str, what: str, trust_code: bool) -> None:
    """Refuse to run ``content`` unless the user consented.

    Args:
        content: the code's bytes (checked against the files the user named).
        name: its attribute (``attr``, or ``module:attr`` for a module).
        what: the message's subject, naming the file (``"run R: its model copy F"``).
        trust_code: the user's explicit consent.

    Raises:
        UntrustedCodeError: naming ``what`` and how to consent.
    """
    if trust_code or has_consent(content, name):
        return
    raise UntrustedCodeError(
        f"{what} is code, not one of jaxcal's registered models: loading it would "
        f"run it, and it is not run without your consent; {HOW_TO_CONSENT}"
    )
