"""The documentation works: every code block of README.md and docs/ runs or is
checked, its links hold, and the site builds with warnings as errors.

* Python blocks run, a page's blocks in order in one namespace (a block may use what
  an earlier one built), in a temporary working directory. A block marked
  ``<!-- not run: <reason> -->`` on the line above (a trained run folder, a cluster, a
  long compilation) is compiled only. A block with a ``jaxcal.calibrate(...,
  method="...")  # or ...`` call is run by tests/test_readme.py with each method its
  comment names, and compiled here.
* Bash blocks: every ``python -m jaxcal.<tool>`` names a module that exists and, for
  the tools with a parser, arguments it accepts; every ``make <target>`` is a target of
  the Makefile.
* A root-relative link (``/results/...``: a file of the repository, not of the site)
  and every relative link of the README name existing files.
* ``mkdocs build --strict`` (``make docs``) succeeds without a warning, and the site
  loads nothing from the network.
"""

import importlib.util
import pathlib
import re
import shlex
import subprocess
import sys
from typing import NamedTuple

import pytest
from test_readme import CALL, RUN

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^```(\w*)\n(.*?)^```\s*$", re.M | re.S)
NOT_RUN = re.compile(r"^<!-- not run: (.+?) -->$")


class Block(NamedTuple):
    page: pathlib.Path
    line: int  # the fence's line (1-based)
    lang: str
    source: str
    not_run: str | None  # the marker's reason


def blocks(page: pathlib.Path) -> list[Block]:
    text = page.read_text()
    lines = text.splitlines()
    found = []
    for match in FENCE.finditer(text):
        line = text.count("\n", 0, match.start()) + 1
        above = lines[line - 2] if line > 1 else ""
        marker = NOT_RUN.match(above)
        found.append(
            Block(page, line, match[1], match[2], marker[1] if marker else None)
        )
    return found


def _name(page: pathlib.Path) -> str:
    return str(page.relative_to(ROOT))


def _python_pages():
    return [
        pytest.param(page, id=_name(page))
        for page in PAGES
        if any(b.lang == "python" for b in blocks(page))
    ]


def _fleet_results(namespace, tmp_path):
    """docs/fleet.md's blocks calibrated its 6 units of the nominal model."""
    import numpy as np

    out, stats = namespace["out"], namespace["stats"]
    assert out.theta.shape == (6, 40, 1) and np.isfinite(out.theta).all()
    assert abs(out.theta[:, -1]).max() < 0.01  # fouling 0: the nominal model
    assert stats["num_units"] == 6 and stats["num_rows"] == 240
    assert (tmp_path / "out.h5").is_file()


# what a page's blocks computed, beyond running
RESULTS = {"docs/fleet.md": _fleet_results}


@pytest.mark.parametrize("page", _python_pages())
def test_python_blocks_run(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a block may write files (fleet.md: out.h5)
    namespace = {"__name__": "__docs__"}
    for block in (b for b in blocks(page) if b.lang == "python"):
        # padded so that a traceback names the line of the page
        source = "\n" * block.line + block.source
        code = compile(source, _name(page), "exec")
        if block.not_run is not None:
            continue
        if CALL.search(block.source):
            assert block.source in RUN, (
                f"{_name(page)}:{block.line}: a calibrate block that "
                "tests/test_readme.py does not run"
            )
            continue
        exec(code, namespace)  # noqa: S102
    if _name(page) in RESULTS:
        RESULTS[_name(page)](namespace, tmp_path)


def test_not_run_markers_give_a_reason_above_a_python_block():
    for page in PAGES:
        marked = [b for b in blocks(page) if b.not_run is not None]
        assert all(b.lang == "python" for b in marked), _name(page)
        assert all(len(b.not_run.split()) >= 4 for b in marked), _name(page)
        markers = len(re.findall(r"^<!-- not run:", page.read_text(), re.M))
        assert markers == len(marked), f"{_name(page)}: a marker above no block"


def _parsers():
    """``{module: parse(args)}`` of the command lines with a parser of their own."""
    from jaxcal.cli import diagnose, evaluate, fleet, generate, train

    return {
        "jaxcal.train": train.parse_args,
        "jaxcal.evaluate": evaluate.parse_args,
        "jaxcal.generate": generate.parse_args,
        "jaxcal.fleet": fleet.parse_args,
        "jaxcal.diagnose": diagnose.parse_args,
    }


def shell_commands(source: str) -> list[list[str]]:
    """The commands of a bash block as argument lists: comments dropped, continued
    lines joined, a right-hand column (two hosts side by side) dropped, ``<...>``
    placeholders and ``$i`` given a value, ``[optional]`` arguments kept."""
    lines = []
    for raw in source.splitlines():
        left = re.split(r"(?<=\S)\s{8,}(?=\S)", raw)[0]
        lines.append(re.sub(r"(^|\s)#.*", "", left).rstrip())
    text = "\n".join(lines).replace("\\\n", " ")
    text = re.sub(r"<[^>]*>", "x", text).replace("$i", "0")
    text = re.sub(r"\[([^\]=\s]+=[^\]\s]*)\]", r"\1", text)
    commands = []
    for line in text.splitlines():
        for part in re.split(r"\s*(?:;|&&|&|\|)\s*", line):
            if part.strip():
                commands.append(shlex.split(part))
    return commands


def _commands():
    """``(where, argv)`` of every command of the pages: bash blocks' lines and inline
    code spans `python -m jaxcal...` / `make ...` (those without arguments too)."""
    for page in PAGES:
        for block in (b for b in blocks(page) if b.lang == "bash"):
            for cmd in shell_commands(block.source):
                yield f"{_name(page)}:{block.line}", cmd
        for span in re.findall(
            r"`((?:python -m jaxcal[\w.]*|make [\w-]+)(?: [^`]*)?)`", page.read_text()
        ):
            yield f"{_name(page)}: `{span}`", shlex.split(span)


def test_shell_commands_name_existing_tools_and_arguments(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # an output path is checked against the cwd
    parsers = _parsers()
    targets = set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M))
    seen = set()
    for where, cmd in _commands():
        where = f"{where}: {' '.join(cmd)}"
        if cmd[0] == "make":
            assert cmd[1] in targets, where
            seen.add("make")
        if "-m" not in cmd or not cmd[cmd.index("-m") + 1].startswith("jaxcal"):
            continue
        at = cmd.index("-m") + 1
        module, args = cmd[at], cmd[at + 1 :]
        assert importlib.util.find_spec(module) is not None, where
        if module in parsers and args:  # a bare tool name in the prose: no args
            try:
                parsers[module](args)
            except ValueError as err:
                pytest.fail(f"{where}: {err}")
            seen.add(module)
    assert seen == {"make", *parsers}  # each parser is exercised at least once


def test_shell_commands_reader_takes_the_pages_forms():
    block = """# host A                 # host B
XLA_FLAGS=x \\
  python -m jaxcal.fleet data=a.h5 \\        python -m jaxcal.fleet data=a.h5 \\
  out=b.h5 --process-id $i &                 out=b.h5 --process-id 1
python -m jaxcal.evaluate run=runs/<run name> [data=other.csv]   # a comment
for i in 0 1; do
  make paper PRESET=quick; done; wait
"""
    assert shell_commands(block) == [
        ["XLA_FLAGS=x", "python", "-m", "jaxcal.fleet", "data=a.h5", "out=b.h5"]
        + ["--process-id", "0"],
        ["python", "-m", "jaxcal.evaluate", "run=runs/x", "data=other.csv"],
        ["for", "i", "in", "0", "1"],
        ["do"],
        ["make", "paper", "PRESET=quick"],
        ["done"],
        ["wait"],
    ]


def test_links_name_existing_files():
    for page in PAGES:
        text = page.read_text()
        for target in re.findall(r"\]\((/[^)#\s]+)", text):  # repository files
            assert (ROOT / target.lstrip("/")).exists(), f"{_name(page)}: {target}"
    readme = (ROOT / "README.md").read_text()
    for target in re.findall(r"\]\(([^)#\s:]+)", readme):
        assert (ROOT / target).exists(), f"README.md: {target}"


def test_readme_opens_with_the_two_commands_then_one_example_then_the_pages():
    readme = (ROOT / "README.md").read_text()
    sections = re.findall(r"^## (.+)$", readme, re.M)
    assert sections == ["Two commands", "Bring your own model", "Documentation"]
    first = blocks(ROOT / "README.md")[0]
    assert first.lang == "bash"
    assert [c[:2] for c in shell_commands(first.source)] == [
        ["make", "train"],
        ["make", "test"],
    ]
    assert "python -m jaxcal.train dataset=cmapss" in first.source
    assert [b.lang for b in blocks(ROOT / "README.md")] == ["bash", "python"]
    linked = set(re.findall(r"\]\((docs/[^)#]+\.md)", readme))
    guide = {f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")}
    assert guide | {"docs/api/index.md"} <= linked


def test_site_builds_strictly_and_offline(tmp_path):
    site = tmp_path / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log
    assert "WARNING" not in log, log
    pages = {str(p.relative_to(site)) for p in site.rglob("*.html")}
    for page in (ROOT / "docs").rglob("*.md"):
        assert str(page.relative_to(ROOT / "docs").with_suffix(".html")) in pages
    api = (site / "api/front.html").read_text()
    for name in (
        "model.Model",
        "calibrators.front.door.calibrate",
        "data.readers.read_dataset",
    ):
        assert f'id="jaxcal.{name}"' in api, name
    assert ":class:`" not in api  # Sphinx roles read as code (docs/_ext)
    for page in site.rglob("*.html"):  # nothing fetched when a page is viewed
        fetched = re.findall(
            r'(?:src|href)="(https?://[^"]+\.(?:js|css))"', page.read_text()
        )
        assert not fetched, (page, fetched)
