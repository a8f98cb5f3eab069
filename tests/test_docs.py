"""The documentation stands on its own: no pointers to pages users do not have, no broken
relative links, and docs/formats.md's word examples are what the code prints."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from compd.cli import main

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FORMATS = ROOT / "docs" / "formats.md"
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _user_files() -> list[Path]:
    files = list(DOCS)
    for folder in ("compd", "hil_sim", "scripts"):
        files += [p for p in (ROOT / folder).rglob("*") if p.suffix in (".py", ".md", ".yaml") and p.is_file()]
    return files


def test_no_file_points_at_pages_outside_the_repository():
    bad = []
    for p in _user_files():
        text = p.read_text(encoding="utf-8")
        for needle in ("CONTRACT.md", "SPEC.md", "SPEC §"):
            if needle in text:
                bad.append(f"{p.relative_to(ROOT)}: {needle}")
    assert not bad, bad


def _slug(title: str) -> str:
    """The anchor a heading gets on GitHub (lower case, punctuation dropped, spaces → '-')."""
    return re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    return {_slug(m.group(1)) for m in re.finditer(r"^#+\s+(.*)$", text, flags=re.M)}


@pytest.mark.parametrize("page", DOCS, ids=lambda p: p.name)
def test_relative_links_point_at_files_that_exist(page):
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    bad = []
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            bad.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(f"{target}: no such heading in {dest.name}")
    assert not bad, bad


def _examples(command: str) -> list[tuple[list[str], list[str]]]:
    """Each `$ compd COMMAND ...` line of formats.md's code blocks and the lines printed below it."""
    out = []
    lines = FORMATS.read_text(encoding="utf-8").splitlines()
    for i, line in enumerate(lines):
        if line.startswith(f"$ compd {command} "):
            printed = []
            for nxt in lines[i + 1 :]:
                if nxt.startswith("$ ") or nxt.startswith("```"):
                    break
                printed.append(nxt)
            out.append((shlex.split(line[2:])[1:], printed))
    return out


def _run(argv: list[str]) -> list[str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    return buf.getvalue().splitlines()


def test_formats_md_has_the_papers_word_example():
    argv = [a for a, _ in _examples("encode")]
    assert ["encode", "5", "-3"] in argv


@pytest.mark.parametrize("command", ["encode", "decode"])
def test_formats_md_word_examples_are_what_the_cli_prints(command):
    examples = _examples(command)
    assert examples
    for argv, printed in examples:
        assert _run(argv) == printed, argv


def test_formats_md_encoder_walk_is_what_the_encoder_does():
    text = FORMATS.read_text(encoding="utf-8")
    m = re.search(r"\$ cat walk\.py\n(.*?)\$ python walk\.py\n(.*?)```", text, flags=re.S)
    assert m, "the Encoder walk example is missing"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        exec(compile(m.group(1), "walk.py", "exec"), {})  # noqa: S102 - our own doc's example
    assert buf.getvalue() == m.group(2)
