"""The documentation says what the library says.

- every result-code table in the docs (a Markdown table headed `| code | name | …`) lists
  exactly the codes and names of `lievi.RESULTS` (or, for a table of fit reasons, of
  `lievi.FIT_REASONS`), read from the library at test time;
- every message the docs quote from the library — a code comment `# "…"` / `# '…'` after
  `.message(…)` / `.messages()`, continued on the comment lines below it, with `(...)` or
  `...` for what is left out — is text the library holds (its string constants).
"""

import ast
import re
from pathlib import Path

import pytest

import lievi

ROOT = Path(__file__).resolve().parent.parent
PAGES = sorted(p for p in (ROOT / "docs").rglob("*.md") if "notebooks" not in p.parts)
PAGES.append(ROOT / "README.md")


def codes(cls) -> dict[str, int]:
    return {
        name: value
        for name, value in vars(cls).items()
        if not name.startswith("_") and isinstance(value, int) and not isinstance(value, bool)
    }


# ---- result-code tables -------------------------------------------------------------------

HEADER = re.compile(r"^\|\s*code\s*\|\s*name\s*\|", re.I)
ROW = re.compile(r"^\|\s*(\d+)\s*\|\s*`(\w+)`\s*\|")


def code_tables(text: str) -> list[tuple[int, list[tuple[int, str]]]]:
    """(line number, [(code, name), …]) of every `| code | name | …` table."""
    tables, lines = [], text.splitlines()
    for number, line in enumerate(lines):
        if not HEADER.match(line):
            continue
        rows = []
        for row in lines[number + 2 :]:  # after the |---| line
            if not row.startswith("|"):
                break
            match = ROW.match(row)
            assert match, f"line {number + 1}: a code table row must read | N | `name` | …"
            rows.append((int(match.group(1)), match.group(2)))
        tables.append((number + 1, rows))
    return tables


def check_table(rows: list[tuple[int, str]]) -> list[str]:
    """Differences between a table and the library's codes (empty: the table is right)."""
    names = {name for _, name in rows}
    cls = lievi.FIT_REASONS if "converged" in names else lievi.RESULTS
    expected = codes(cls)
    problems = [
        f"code {code} is `{name}`, but lievi.{cls.__name__}.{name} is {expected.get(name)}"
        for code, name in rows
        if expected.get(name) != code
    ]
    missing = sorted(set(expected) - names, key=expected.get)
    problems += [f"lists no row for lievi.{cls.__name__}.{n} = {expected[n]}" for n in missing]
    if len(cls.messages) != len(expected):
        problems.append(f"lievi.{cls.__name__} has {len(cls.messages)} messages")
    return problems


TABLES = [(page, line, rows) for page in PAGES for line, rows in code_tables(page.read_text())]


def test_the_docs_have_result_code_tables():
    pages = {page.relative_to(ROOT).as_posix() for page, _, _ in TABLES}
    assert {"docs/concepts/failure.md", "docs/guarantees.md"} <= pages


@pytest.mark.parametrize(
    "page, line, rows",
    TABLES,
    ids=[f"{page.relative_to(ROOT).as_posix()}:{line}" for page, line, _ in TABLES],
)
def test_result_code_table_matches_the_library(page, line, rows):
    problems = check_table(rows)
    assert not problems, f"{page.relative_to(ROOT)}:{line}: " + "; ".join(problems)


def test_table_check_can_fail():
    assert check_table([(0, "successful"), (1, "newton_not_converged"), (2, "step_too_large")])
    assert check_table([(0, "successful"), (2, "nonfinite")])
    right = sorted((code, name) for name, code in codes(lievi.RESULTS).items())
    assert not check_table(right)


# ---- quoted messages ---------------------------------------------------------------------


def library_text() -> str:
    """Every string constant of the library's source, whitespace collapsed."""
    strings = []
    for path in sorted((ROOT / "lievi").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                strings.append(node.value)
    return "\n".join(" ".join(s.split()) for s in strings)


QUOTE_START = re.compile(r"\.messages?\(.*?\)\s*#\s*(?:.*?,\s*)?(?P<q>[\"'])(?P<text>.*)$")
ELISION = re.compile(r"\(\s*(?:\.\.\.|…)\s*\)|\.\.\.|…")


def quoted_messages(text: str) -> list[tuple[int, str]]:
    """(line number, quoted text) of the messages quoted in code comments."""
    quotes, lines = [], text.splitlines()
    for number, line in enumerate(lines):
        match = QUOTE_START.search(line)
        if not match:
            continue
        quote, parts = match.group("q"), [match.group("text")]
        following = iter(lines[number + 1 :])
        while quote not in parts[-1]:  # the quote goes on in the comment lines below
            nxt = next(following, "")
            if not nxt.lstrip().startswith("#"):
                break
            parts.append(nxt.lstrip()[1:])
        quotes.append((number + 1, " ".join(parts).split(quote)[0]))
    return quotes


def missing_fragments(quote: str, library: str) -> list[str]:
    fragments = (" ".join(f.split()) for f in ELISION.split(quote))
    return [f for f in fragments if len(f) >= 4 and f not in library]


QUOTES = [(page, line, q) for page in PAGES for line, q in quoted_messages(page.read_text())]


def test_the_docs_quote_messages():
    assert any(page.name == "failure.md" for page, _, _ in QUOTES)


@pytest.mark.parametrize(
    "page, line, quote",
    QUOTES,
    ids=[f"{page.relative_to(ROOT).as_posix()}:{line}" for page, line, _ in QUOTES],
)
def test_quoted_message_is_the_library_text(page, line, quote):
    missing = missing_fragments(quote, library_text())
    assert not missing, f"{page.relative_to(ROOT)}:{line}: the library never says {missing}"


def test_quote_check_can_fail():
    library = library_text()
    text = (
        "lievi.RESULTS.message(2)  # \"the step's group increment left the domain\n"
        "#  of the chart (...). Reduce the step size `h`,\n"
        "#  or use chart='cayley'.\"\n"
    )
    [(_, quote)] = quoted_messages(text)
    assert missing_fragments(quote, library)
    assert not missing_fragments(RESULTS_2_START + " (...) Reduce the step size `h`.", library)


RESULTS_2_START = "the step is too large for the method:"
