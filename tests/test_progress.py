"""Progress bars: whole lines (no carriage return) in a log, tqdm on a terminal."""

import io

from tqdm.std import tqdm as std_tqdm

from jaxcal.progress import LogLines, is_terminal, progress_bar


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_a_log_gets_one_line_per_stage_and_no_carriage_return():
    log = io.StringIO()
    bar = progress_bar(
        total=3, desc="calibrate", file=log, leave=False,
        bar_format="{desc} ({n}/{total} steps)",
    )  # fmt: skip
    assert isinstance(bar, LogLines)
    for stage in ("screening", "building ukf", "unit group 1"):
        bar.set_description_str(stage, False)  # as jaxcal.calibrate does
        bar.update()
    bar.close()
    text = log.getvalue()
    assert "\r" not in text
    assert text.splitlines() == [
        "calibrate (0/3 steps)",
        "screening (0/3 steps)",
        "building ukf (1/3 steps)",
        "unit group 1 (2/3 steps)",
    ]


def test_a_long_stage_is_a_few_lines_and_a_kept_bar_ends_with_its_count():
    log = io.StringIO()
    with progress_bar(range(1000), desc="fit", file=log, bar_format="{desc} {n}") as b:
        for _ in b:
            pass
    # the default interval between two lines of a stage holds back 1000 updates
    assert log.getvalue().splitlines() == ["fit 0", "fit 1000"]


def test_a_delayed_bar_writes_nothing_before_its_delay():
    log = io.StringIO()
    bar = progress_bar(total=2, desc="late", file=log, delay=1e6)
    bar.set_description_str("stage")
    bar.update(2)
    bar.close()
    assert log.getvalue() == ""


def test_a_terminal_keeps_tqdm_updating_its_line():
    tty = _Terminal()
    assert is_terminal(tty) and not is_terminal(io.StringIO())
    bar = progress_bar(total=2, desc="x", file=tty, mininterval=0)
    assert not isinstance(bar, LogLines) and isinstance(bar, std_tqdm)
    bar.update(2)
    bar.close()
    assert "\r" in tty.getvalue()


def test_a_disabled_bar_is_silent():
    log = io.StringIO()
    for _ in progress_bar(range(3), file=log, disable=True):
        pass
    bar = progress_bar(total=2, file=log, disable=True)  # calibrate(progress=False)
    bar.set_description_str("stage", False)
    bar.update()
    bar.close()
    assert log.getvalue() == ""


def test_calibrate_writes_a_line_per_stage_to_a_captured_stderr(monkeypatch, capsys):
    """``jaxcal.calibrate``'s progress into a stream that is not a terminal."""
    import jax.numpy as jnp
    import numpy as np
    import pandas as pd

    import jaxcal
    from jaxcal.calibrators.front import door as front

    monkeypatch.setattr(front, "PROGRESS_AFTER", 0.0)  # show it from the start
    model = jaxcal.Model.from_function(
        lambda w, th: jnp.stack([th[0] * w[0]]), conditions=("u",),
        parameters={"a": (1.0, 0.5, 2.0)}, outputs=("y",),
    )  # fmt: skip
    u = np.linspace(1.0, 2.0, 20)
    data = pd.DataFrame({"u": u, "y": 1.2 * u + 0.01 * np.sin(7 * u)})
    jaxcal.calibrate(model, data, method="ls", noise=0.01)
    err = capsys.readouterr().err
    assert "\r" not in err
    stages = [line for line in err.splitlines() if line.startswith("jaxcal.calibrate")]
    assert any("screening" in line for line in stages), err
    assert any("building ls" in line for line in stages), err
