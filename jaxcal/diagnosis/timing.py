"""The diagnosis's stages timed, with a progress line as each starts.

A fleet diagnosis runs for minutes; a user watching it (or its log) should see which
stage it is in, and the report should say where the time went, so that a slow run can be
read without a profiler. :class:`StageClock` keeps the wall seconds of each named stage
(a stage entered twice adds up) and writes one progress line when a stage starts and,
within a long stage, at most one per :data:`jaxcal.progress.LOG_EVERY` seconds as its
batches advance (:func:`jaxcal.progress.progress_bar`: whole lines in a log, tqdm's line
on a terminal). :func:`batch_progress` is how work deep in a stage (the model evaluated
over the fleet's rows, batch after batch) reports its batches without the clock being
passed down to it.
"""

from __future__ import annotations

import contextlib
import contextvars
import time

from jaxcal.progress import progress_bar

# the clock of the diagnosis running in this context (None: nobody is watching)
_ACTIVE: contextvars.ContextVar[StageClock | None] = contextvars.ContextVar(
    "jaxcal_diagnosis_clock", default=None
)


class StageClock:
    """Wall seconds per stage, and the progress lines (``progress=False``: none)."""

    def __init__(self, progress: bool = False, file=None):
        self.seconds: dict[str, float] = {}
        self._start = time.perf_counter()
        self._bar = (
            progress_bar(desc="diagnosis", unit=" batches", file=file, leave=True)
            if progress
            else None
        )
        self._token = _ACTIVE.set(self)

    @contextlib.contextmanager
    def stage(self, name: str):
        """Time the block as stage ``name`` (its line is written as it starts)."""
        if self._bar is not None:
            self._bar.set_description_str(f"diagnosis: {name}")
        begin = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + (
                time.perf_counter() - begin
            )

    def batch(self, done: int, total: int, what: str) -> None:
        """``done`` of ``total`` ``what`` of the current stage are through."""
        if self._bar is not None:
            self._bar.set_postfix_str(f"{what} {done}/{total}", refresh=False)
            self._bar.update(1)

    def timings(self) -> dict[str, float]:
        """``{stage: seconds, ..., "total": seconds}`` (stages in the order run)."""
        out = {k: round(v, 3) for k, v in self.seconds.items()}
        out["total"] = round(time.perf_counter() - self._start, 3)
        return out

    def close(self) -> None:
        """End the progress display and stop answering :func:`batch_progress`."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        with contextlib.suppress(ValueError):  # closed in another context
            _ACTIVE.reset(self._token)


def batch_progress(done: int, total: int, what: str = "rows") -> None:
    """Report a batch of the running diagnosis's current stage (no-op outside
    one)."""
    clock = _ACTIVE.get()
    if clock is not None:
        clock.batch(done, total, what)
