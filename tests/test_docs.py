"""Every citation of the documentation in code and Markdown points at a page and a section
that exist, so comments cannot drift away from ``docs/`` silently."""

from __future__ import annotations

import argparse
import ast
import re
import shlex
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
SCANNED = ("csa_core", "server", "client", "tests", "benchmarks", "docs")
# docs/<page>.md, then optionally quoted section names: "A", "B" and "C"
CITATION = re.compile(r'docs/([\w-]+\.md)`?[,\s(]*((?:"[^"\n]+"(?:\s*,\s*|\s+and\s+)?)*)')
HEADING = re.compile(r"^#+\s+(?:\d+\.\s+)?(.+?)\s*$", re.MULTILINE)


def citations(text: str) -> list[tuple[str, list[str]]]:
    """(page, [sections]) of every docs/ citation in ``text``."""
    return [(page, re.findall(r'"([^"]+)"', quoted)) for page, quoted in CITATION.findall(text)]


def headings(page: Path) -> set[str]:
    return set(HEADING.findall(page.read_text()))


def test_citations_are_parsed_with_all_their_sections():
    text = (
        'see docs/method.md "Predict", "Fuse in 3D" and "Adapt"; '
        '`docs/data-contract.md` ("The scene folder")'
    )
    assert citations(text) == [
        ("method.md", ["Predict", "Fuse in 3D", "Adapt"]),
        ("data-contract.md", ["The scene folder"]),
    ]
    assert "Predict" in headings(DOCS / "method.md")  # numbered headings count by their name


def test_every_cited_page_and_section_exists():
    files = [REPO / "README.md"]
    for top in SCANNED:
        files += [p for p in (REPO / top).rglob("*") if p.suffix in (".py", ".md")]
    cited, missing = 0, []
    for path in files:
        for page, sections in citations(path.read_text(errors="replace")):
            cited += 1
            target = DOCS / page
            if not target.is_file():
                missing.append(f"{path.relative_to(REPO)}: docs/{page} does not exist")
                continue
            missing += [
                f"{path.relative_to(REPO)}: docs/{page} has no section {s!r}"
                for s in sections
                if s not in headings(target)
            ]
    assert cited >= 50  # the code does cite the documentation
    assert missing == []


# benchmarks/RESULTS.md "A", benchmarks/results/<page>.md "A", "B" (or the short RESULTS "A"): a
# section is cited by the start of its heading
RESULTS_CITATION = re.compile(
    r'(benchmarks/RESULTS\.md|benchmarks/results/[\w-]+\.md|\bRESULTS\b)`?[,\s(]*((?:"[^"\n]+"(?:\s*,\s*|\s+and\s+)?)*)'
)


def results_citations(text: str) -> list[tuple[str, list[str]]]:
    """(page relative to the repository, [sections]) of every citation of the measurements."""
    found = []
    for page, quoted in RESULTS_CITATION.findall(text):
        page = "benchmarks/RESULTS.md" if page == "RESULTS" else page
        found.append((page, re.findall(r'"([^"]+)"', quoted)))
    return found


def test_results_citations_are_parsed_with_their_page():
    text = (
        'see benchmarks/results/fusion.md "Far depth outliers", "Flying pixels" and '
        'RESULTS "Targets"; `benchmarks/results/speed.md` ("A cheaper march")'
    )
    assert results_citations(text) == [
        ("benchmarks/results/fusion.md", ["Far depth outliers", "Flying pixels"]),
        ("benchmarks/RESULTS.md", ["Targets"]),
        ("benchmarks/results/speed.md", ["A cheaper march"]),
    ]


def test_every_cited_results_section_exists():
    """Citations of the index ``benchmarks/RESULTS.md`` and of its pages under
    ``benchmarks/results/`` (by the start of the heading, quotes in a heading left out) point
    at a page and a heading that exist."""
    files = [REPO / "README.md"]
    for top in SCANNED:
        files += [p for p in (REPO / top).rglob("*") if p.suffix in (".py", ".md")]
    cited, missing = 0, []
    for path in files:
        if path == Path(__file__).resolve():
            continue  # this file's examples
        for page, sections in results_citations(path.read_text(errors="replace")):
            target = REPO / page
            if not target.is_file():
                missing.append(f"{path.relative_to(REPO)}: {page} does not exist")
                continue
            heads = {h.replace('"', "") for h in headings(target)}
            for section in sections:
                cited += 1
                if not any(h.startswith(section) for h in heads):
                    missing.append(f"{path.relative_to(REPO)}: {page} has no section {section!r}")
    assert cited >= 50  # the code and the docs do cite the measurements
    assert missing == []


def test_results_pages_are_listed_in_the_index():
    index = (REPO / "benchmarks" / "RESULTS.md").read_text()
    pages = sorted((REPO / "benchmarks" / "results").glob("*.md"))
    assert pages
    assert [p.name for p in pages if f"(results/{p.name})" not in index] == []


def test_no_code_cites_the_old_design_notes():
    offending = [
        f"{p.relative_to(REPO)}:{n}"
        for top in ("csa_core", "server", "client", "benchmarks")
        for p in (REPO / top).rglob("*.py")
        for n, line in enumerate(p.read_text().splitlines(), start=1)
        if "DESIGN.md" in line
    ]
    assert offending == []


CODE_NAME = re.compile(r"`((?:csa_core|server|client)(?:\.\w+)+)`")
CODE_PATH = re.compile(r"\b((?:csa_core|server|client|tests|benchmarks)/[\w./-]+\.py)\b")


def defined_names(source: str) -> dict[str, set[str]]:
    """Top-level names of a module (functions, classes, assignments) with each class's own names."""
    names: dict[str, set[str]] = {}
    for node in ast.parse(source).body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            names[node.name] = set()
        elif isinstance(node, ast.ClassDef):
            names[node.name] = {
                getattr(n, "name", None) or getattr(getattr(n, "target", None), "id", "")
                for n in node.body
            }
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                if isinstance(target, ast.Name):
                    names[target.id] = set()
    return names


def resolves(dotted: str) -> bool:
    """Whether ``a.b.c.Name.attr`` names a module, or a name defined in one (statically: no import).
    Names a package re-exports lazily count when its ``__init__`` lists them."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        base = REPO.joinpath(*parts[:cut])
        module = (
            base.with_suffix(".py") if base.with_suffix(".py").is_file() else base / "__init__.py"
        )
        if not module.is_file():
            continue
        rest = parts[cut:]
        if not rest:
            return True
        source = module.read_text()
        names = defined_names(source)
        if rest[0] not in names:
            return module.name == "__init__.py" and len(rest) == 1 and f'"{rest[0]}"' in source
        return len(rest) == 1 or (len(rest) == 2 and rest[1] in names[rest[0]])
    return False


def test_code_named_in_the_docs_exists():
    stale = []
    for page in sorted(DOCS.glob("*.md")):
        text = page.read_text()
        stale += [
            f"{page.name}: `{n}`" for n in sorted(set(CODE_NAME.findall(text))) if not resolves(n)
        ]
        stale += [
            f"{page.name}: {p}"
            for p in sorted(set(CODE_PATH.findall(text)))
            if not (REPO / p).is_file()
        ]
    assert stale == []


# A line of a fenced code block that runs `csa` or `csa-client`, after any VAR=value prefixes.
COMMAND_LINE = re.compile(r"^(?:[A-Za-z_]\w*=\S*\s+)*(csa|csa-client)(?:\s|$)")
FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)


def quoted_commands(text: str) -> Iterator[tuple[str, list[str]]]:
    """(program, arguments) of every `csa ...` or `csa-client ...` line in the fenced code
    blocks of ``text``: continuation lines joined, comments and VAR=value prefixes dropped."""
    for block in FENCE.findall(text):
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            line = line.strip()
            if not COMMAND_LINE.match(line):
                continue
            words = shlex.split(line, comments=True)
            while re.match(r"^[A-Za-z_]\w*=", words[0]):
                words.pop(0)
            yield words[0], words[1:]


def test_quoted_commands_are_found():
    text = (
        "```bash\nexport CSA_URL=x\ncsa data synth runs/r --seed 0   # rooms\n"
        "CSA_EXECUTOR=ray csa-client jobs 3 \\\n    --log\nray start --head\n```\n"
        "outside a block: csa nerf fit x\n"
    )
    assert list(quoted_commands(text)) == [
        ("csa", ["data", "synth", "runs/r", "--seed", "0"]),
        ("csa-client", ["jobs", "3", "--log"]),
    ]


def parsers() -> dict[str, argparse.ArgumentParser]:
    """The real parsers of both commands, built without running anything."""
    from client.cli import build_parser as client_parser
    from csa_core.cli.main import build_parser as csa_parser

    return {"csa": csa_parser(), "csa-client": client_parser()}


def test_every_quoted_command_parses(capsys):
    """Every `csa ...` and `csa-client ...` command shown in a code block of the README and
    of docs/ is accepted by the command's own argument parser, so a reader who copies one
    does not meet an unknown command or flag."""
    pytest.importorskip("fastapi")  # `csa serve` comes from the server package
    programs = parsers()
    pages = [REPO / "README.md", *sorted(DOCS.glob("*.md"))]
    checked, refused = 0, []
    for page in pages:
        for program, args in quoted_commands(page.read_text()):
            checked += 1
            try:
                programs[program].parse_args(args)
            except SystemExit:
                error = capsys.readouterr().err.strip().splitlines()[-1:]
                refused.append(f"{page.relative_to(REPO)}: {program} {' '.join(args)}: {error}")
    assert checked >= 40  # the README and the docs do show commands
    assert refused == []
