"""Issue 38: every command the README and docs show exists, as written (docs/api.md once named
`optitac-edge boards`, a command there is not; deploy.md gave a range of protocols the CLI refuses)."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from optitac_edge.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
#: Options whose value a synopsis names by a capital placeholder (``--rotation-deg A``): a number stands in.
NUMERIC = ("--rotation-deg", "--minutes", "--duration", "--limit", "--seed", "--sensor", "--frames", "--fps")


def _as_written(line: str) -> str:
    """A synopsis line as a user would type it: optional parts given, the first of alternatives, a number for
    a numeric placeholder; a trailing comment dropped."""
    line = line.split(" #")[0].strip()
    line = re.sub(r"\[([^\[\]]*)\]", r"\1", line)
    line = re.sub(r"(\S+?)\|\S+", r"\1", line)
    return re.sub(rf"({'|'.join(NUMERIC)}) [A-Z]+\b", r"\1 1", line)


def _command_lines() -> list[tuple[str, str]]:
    """Every ``optitac-edge …`` of a fenced shell block, with its page."""
    out = []
    for page in PAGES:
        for block in re.findall(r"```(?:sh|bash|console|shell)?\n(.*?)```", page.read_text(), re.DOTALL):
            for line in block.replace("\\\n", " ").splitlines():
                for part in re.split(r"&&|;|\|\|| \| ", line):
                    part = re.sub(r"^\$ ", "", part.strip())
                    if part.startswith("optitac-edge "):
                        out.append((page.name, _as_written(part)))
    return out


def _named_commands() -> set[tuple[str, ...]]:
    """Every command (and calibration step) an inline ``optitac-edge …`` of the pages names."""
    names = set()
    for page in PAGES:
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.DOTALL)
        for span in re.findall(r"`optitac-edge ([a-z][a-z0-9-]*)(?: ([a-z][a-z0-9-]*))?", text):
            names.add(span if span[0] == "calibrate" and span[1] else (span[0],))
    return names


def _parses(args: list[str]) -> str:
    """'' when the CLI's parser takes ``args``, else its one line of error."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            build_parser().parse_args(args)
    except SystemExit as exc:
        if exc.code:
            return err.getvalue().strip().splitlines()[-1]
    return ""


LINES = _command_lines()


def test_the_pages_show_commands() -> None:
    assert len(LINES) > 40 and len(_named_commands()) > 15


@pytest.mark.parametrize(("page", "line"), LINES, ids=[f"{p}:{k}" for k, (p, _) in enumerate(LINES)])
def test_every_command_line_of_the_docs_parses(page: str, line: str) -> None:
    assert _parses(shlex.split(line)[1:]) == "", f"{page}: {line}"


@pytest.mark.parametrize("command", sorted(_named_commands()))
def test_every_command_the_docs_name_exists(command: tuple[str, ...]) -> None:
    assert _parses([*command, "--help"]) == "", command


def test_a_command_that_does_not_exist_is_caught() -> None:
    """The check itself: the command docs/api.md once named."""
    assert "invalid choice: 'boards'" in _parses(["boards", "--help"])
    assert _parses(shlex.split(_as_written("optitac-edge evaluate REC --cal CAL [--strict]"))[1:]) == ""
