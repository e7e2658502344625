"""Every citation of the documentation in code and Markdown points at a page and a section
that exist, so comments cannot drift away from ``docs/`` silently."""

from __future__ import annotations

import ast
import re
from pathlib import Path

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
    text = 'see docs/method.md "Predict", "Fuse in 3D" and "Adapt"; `docs/data-contract.md` ("The scene folder")'
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


# benchmarks/RESULTS.md "A" or RESULTS "A", "B": a section is cited by the start of its heading
RESULTS_CITATION = re.compile(r'(?:benchmarks/RESULTS\.md|RESULTS)`?[,\s(]*((?:"[^"\n]+"(?:\s*,\s*|\s+and\s+)?)*)')


def test_every_cited_results_section_exists():
    """Citations of ``benchmarks/RESULTS.md`` sections (by the start of the heading, quotes in
    a heading left out) point at a heading that exists."""
    heads = {h.replace('"', "") for h in headings(REPO / "benchmarks" / "RESULTS.md")}
    files = [REPO / "README.md"]
    for top in SCANNED:
        files += [p for p in (REPO / top).rglob("*") if p.suffix in (".py", ".md")]
    cited, missing = 0, []
    for path in files:
        for quoted in RESULTS_CITATION.findall(path.read_text(errors="replace")):
            for section in re.findall(r'"([^"]+)"', quoted):
                cited += 1
                if not any(h.startswith(section) for h in heads):
                    missing.append(f"{path.relative_to(REPO)}: benchmarks/RESULTS.md has no section {section!r}")
    assert cited >= 50  # the code and the docs do cite the measurements
    assert missing == []


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
        module = base.with_suffix(".py") if base.with_suffix(".py").is_file() else base / "__init__.py"
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
        stale += [f"{page.name}: `{n}`" for n in sorted(set(CODE_NAME.findall(text))) if not resolves(n)]
        stale += [f"{page.name}: {p}" for p in sorted(set(CODE_PATH.findall(text))) if not (REPO / p).is_file()]
    assert stale == []
