"""The project's texts: every relative link and image in README.md and docs/ resolves (to a
file, and for `#anchor` links to a heading of the Markdown file they name), every
`flamenerf X` command that the README shows exists (`flamenerf X --help` exits 0), and no
text speaks of how the project was developed (work sessions, numbered tickets)."""

from __future__ import annotations

import contextlib
import io
import re
import subprocess
from pathlib import Path

import pytest

from flamenerf.cli import main

ROOT = Path(__file__).resolve().parent.parent

FENCE = re.compile(r"^(```|~~~)")
# [text](target) and ![alt](target); the text may hold one level of brackets
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
INLINE_CODE = re.compile(r"(`+)(.+?)\1")
HEADING = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")


def markdown_files() -> list[Path]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    files += [p for p in [ROOT / "CHANGELOG.md"] if p.exists()]
    return files


def prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line.strip()):
            fenced = not fenced
            continue
        if not fenced:
            out.append(line)
    return out


def code_blocks(text: str) -> list[str]:
    blocks, current = [], None
    for line in text.splitlines():
        if FENCE.match(line.strip()):
            if current is None:
                current = []
            else:
                blocks.append("\n".join(current))
                current = None
        elif current is not None:
            current.append(line)
    return blocks


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: its rendered text lower-cased, punctuation other than
    hyphens and underscores dropped, spaces made hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link: its text
    text = text.replace("`", "").replace("*", "")
    return re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in prose_lines(path.read_text(encoding="utf-8")):
        m = HEADING.match(line)
        if not m:
            continue
        base = slug(m.group(2))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(path: Path) -> list[str]:
    out = []
    for line in prose_lines(path.read_text(encoding="utf-8")):
        line = INLINE_CODE.sub("", line)
        out += LINK.findall(line)
    return out


@pytest.mark.parametrize("doc", markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_and_images_resolve(doc: Path):
    bad = []
    for target in links(doc):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        dest = (doc.parent / file_part).resolve() if file_part else doc
        if not dest.exists():
            bad.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor.lower() not in anchors(dest):
            bad.append(f"{target}: no heading with that anchor in {dest.name}")
    assert not bad, f"{doc.relative_to(ROOT)}: " + "; ".join(bad)


def test_slugs_follow_github():
    assert slug("`flamenerf track VIDEO --out EXPR.json`") == "flamenerf-track-video---out-exprjson"
    assert slug("FLAME backend (`--face-model flame --flame-dir DIR`)") == \
        "flame-backend---face-model-flame---flame-dir-dir"
    assert slug("The β → mesh model") == "the-β--mesh-model"


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    shown = code_blocks(text)
    shown += [m.group(2) for line in prose_lines(text) for m in INLINE_CODE.finditer(line)]
    names = set()
    for block in shown:
        names.update(re.findall(r"(?:^|[\s/])flamenerf\s+([a-z][a-z-]*)", block, re.M))
    return sorted(names)


def test_the_readme_shows_commands():
    assert {"demo", "preprocess", "train", "render", "view"} <= set(readme_commands())


def test_the_fresh_machine_commands_come_first():
    blocks = code_blocks((ROOT / "README.md").read_text(encoding="utf-8"))
    assert [b.strip() for b in blocks[:2]] == [
        "bash scripts/setup.sh && .venv/bin/flamenerf demo --out demo", "bash scripts/test.sh"]


@pytest.mark.parametrize("name", readme_commands())
def test_readme_command_exists(name: str):
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        try:
            code = main([name, "--help"])
        except SystemExit as e:
            code = e.code
    assert code in (0, None), f"flamenerf {name} --help exited {code}"
    assert "usage" in out.getvalue().lower()


# built from parts so that this file does not match itself
DEV_WORDS = re.compile(r"\b" + "sess" + r"ions?\b", re.I)
TICKETS = re.compile(r"\b" + "iss" + r"ues? ?#?[0-9]+", re.I)
ALLOWED = re.compile(r"""scope\s*=\s*["']""" + "sess" + """ion["']""")


def tracked_texts() -> list[Path]:
    try:
        names = subprocess.run(["git", "ls-files", "*.md", "*.py", "*.sh", "*.toml"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.split()
        files = [ROOT / n for n in names]
    except (OSError, subprocess.CalledProcessError):  # not a git checkout
        files = [p for ext in ("md", "py", "sh", "toml") for p in ROOT.rglob(f"*.{ext}")
                 if ".venv" not in p.parts]
    here = Path(__file__).resolve()
    return [p for p in files if p.exists() and p.resolve() != here]


def test_no_text_speaks_of_how_the_project_was_developed():
    found = []
    for path in tracked_texts():
        for i, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(),
                                 1):
            if TICKETS.search(line) or DEV_WORDS.search(ALLOWED.sub("", line)):
                found.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()[:100]}")
    assert not found, "\n".join(found)
