"""Progress bars that suit where they are written: tqdm's updating line on a terminal,
whole lines in a log file.

tqdm redraws its line with a carriage return. On a terminal that is the point; in a
log file (``python -m jaxcal.train ... 2> train.log``, a batch job, a CI log) every
redraw piles onto one garbled line. :func:`progress_bar` is tqdm on a terminal and,
when its stream is not one, :class:`LogLines`: a tqdm whose every display is a line of
its own, one when a stage starts (a new description) and otherwise at most one per
:data:`LOG_EVERY` seconds. Every progress display of the package comes from here.
"""

from __future__ import annotations

import sys
from typing import Any

from tqdm.auto import tqdm
from tqdm.autonotebook import tqdm as notebook_tqdm
from tqdm.std import tqdm as std_tqdm

LOG_EVERY = 10.0  # s between two lines of one stage in a log


class LogLines(std_tqdm):
    """A tqdm for a stream that is not a terminal: whole lines, no carriage return.

    A line when the description changes (a stage starts), when the bar ends
    (``leave``) and at most every ``mininterval`` seconds (default
    :data:`LOG_EVERY`) in between; a line equal to the last one is not repeated.
    """

    def __init__(self, *args: Any, **kwargs: Any):
        kwargs.setdefault("mininterval", LOG_EVERY)
        kwargs["dynamic_ncols"] = False  # no terminal to measure
        self._last_line = None
        super().__init__(*args, **kwargs)

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        """Write the bar as a line; a clear (``msg=""``) writes nothing."""
        del pos  # lines are never redrawn in place
        line = self.__str__() if msg is None else msg
        if not line or line == self._last_line:
            return False  # False: tqdm's close then writes no "\r"
        self._last_line = line
        self.fp.write(line + "\n")
        self.fp.flush()
        return True

    def set_description_str(self, desc: str | None = None, refresh: bool = True):
        """A new description is a new stage: its line is written now (once the bar's
        ``delay`` has passed), whatever ``refresh`` asks."""
        started = (desc or "") != getattr(self, "desc", "")  # a disabled bar has none
        super().set_description_str(desc, refresh=False)
        if (started or refresh) and self._shown():
            self.refresh()

    def close(self) -> None:
        """The last count as a line of its own (with ``leave``), then tqdm's close,
        told not to redraw."""
        if not self.disable and self._shown():
            leave = abs(self.pos) == 0 if self.leave is None else self.leave
            if leave:
                self.display()
        self.leave = False
        super().close()

    def _shown(self) -> bool:
        """The bar is past its ``delay`` (tqdm shows nothing before)."""
        if self.disable:
            return False
        return self._time() >= self.start_t + self.delay


def is_terminal(stream) -> bool:
    """``stream`` is an interactive terminal (a file, a pipe or pytest's capture is
    not)."""
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty and isatty())
    except (ValueError, OSError):  # a closed stream
        return False


def progress_bar(*args: Any, file=None, **kwargs: Any):
    """A tqdm progress bar on ``file`` (default stderr): tqdm's own
    (:mod:`tqdm.auto`, a notebook widget in Jupyter) on a terminal, :class:`LogLines`
    anywhere else. Arguments as :class:`tqdm.tqdm`."""
    stream = sys.stderr if file is None else file
    if is_terminal(stream) or _in_notebook():
        return tqdm(*args, file=stream, **kwargs)
    return LogLines(*args, file=stream, **kwargs)


def _in_notebook() -> bool:
    """Running in a Jupyter kernel (where tqdm.auto draws a widget, not text):
    tqdm.autonotebook falls back to the text bar everywhere else."""
    return notebook_tqdm is not std_tqdm
