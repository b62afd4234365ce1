"""The documentation is complete and self-contained.

- every public name (`lievi.__all__`, which must equal the explicit re-exports of
  `lievi/__init__.py`) has an entry in the API reference (`docs/api/*.md`), and every
  entry there names something that exists;
- no text in the repository points to documents outside it: the team's working notes or
  this project's tracker numbers (the theory lives in `docs/theory/`; other libraries'
  issues are fine);
- every notebook's plain-text source (`notebooks/*.py`, jupytext percent format) holds the
  same cells as its `.ipynb`.

`mkdocs build --strict` (broken links and references fail) runs in `.ci/run`.
"""

import ast
import json
import re
from pathlib import Path

import pytest

import lievi

ROOT = Path(__file__).resolve().parent.parent
API = ROOT / "docs" / "api"


def explicit_reexports() -> set[str]:
    tree = ast.parse((ROOT / "lievi" / "__init__.py").read_text())
    names = set()
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.level >= 1:
            names |= {a.asname for a in node.names if a.asname is not None and a.asname == a.name}
    return names


def api_entries() -> list[str]:
    entries = []
    for page in sorted(API.glob("*.md")):
        entries += re.findall(r"^::: lievi\.([A-Za-z_][\w.]*)\s*$", page.read_text(), re.M)
    return entries


def test_all_is_the_explicit_reexports():
    assert sorted(lievi.__all__) == sorted(explicit_reexports())


def test_api_reference_covers_every_public_name():
    entries = api_entries()
    missing = sorted(set(lievi.__all__) - {e.split(".")[0] for e in entries})
    assert not missing, f"add `::: lievi.NAME` to a page in docs/api/ for: {missing}"
    duplicated = sorted({e for e in entries if entries.count(e) > 1})
    assert not duplicated, f"documented twice in docs/api/: {duplicated}"
    for entry in entries:
        obj = lievi
        for part in entry.split("."):
            obj = getattr(obj, part)  # AttributeError: the reference names nothing


# Text the repository ships. Other libraries' issues are fine ("jaxlie issue 9", links).
SCANNED = [
    "README.md",
    "CHANGELOG.md",
    "lievi",
    "tests",
    "benchmarks",
    "notebooks",
    "tools",
    "docs",
]
SUFFIXES = {".py", ".md", ".ipynb", ".txt", ".toml", ".yml", ".json"}
NOTES = re.compile("NOTES" + r"(\.md|\s*§)")
ISSUE = re.compile(r"(?<![\w/])(?P<before>\S{1,40}\s+)?[Ii]ssues?\s*#?\s*\d+")
EXTERNAL = {
    "jaxlie",
    "kornia",
    "sophus",
    "jax",
    "equinox",
    "diffrax",
    "optax",
    "scipy",
    "numpy",
    "xla",
}


def shipped_files():
    for name in SCANNED:
        path = ROOT / name
        for f in [path] if path.is_file() else sorted(path.rglob("*")):
            if f.is_file() and f.suffix in SUFFIXES and "results" not in f.parts:
                yield f


def test_no_references_outside_the_repository():
    offending = []
    for f in shipped_files():
        if f.name == "test_docs.py":
            continue
        for number, line in enumerate(f.read_text(errors="replace").splitlines(), 1):
            if NOTES.search(line):
                offending.append(f"{f.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
            # (cheap test first: notebooks hold images as very long base64 lines)
            for match in ISSUE.finditer(line) if "ssue" in line else ():
                before = (match.group("before") or "").strip().strip("(`*[").lower()
                if before not in EXTERNAL and "github.com" not in line:
                    offending.append(f"{f.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    if offending:  # pytest.fail: a plain message, not assert introspection of a long list
        pytest.fail("point into docs/theory/ instead of:\n" + "\n".join(offending))


def test_the_checks_above_can_fail():
    assert NOTES.search("see " + "NOTES" + " §3") and NOTES.search("NOTES" + ".md")
    assert ISSUE.search("the table of " + "iss" + "ue 3")
    match = ISSUE.search("NaN gradient (jaxlie issue 9)")
    assert match.group("before").strip().strip("(").lower() in EXTERNAL


def percent_cells(text: str) -> list[tuple[str, str]]:
    """(cell type, source) of a jupytext percent-format script (no jupytext needed)."""
    cells = []
    for chunk in re.split(r"^# %%", text, flags=re.M)[1:]:
        header, _, body = chunk.partition("\n")
        if "[markdown]" in header:
            lines = [re.sub(r"^# ?", "", line) for line in body.strip("\n").splitlines()]
            cells.append(("markdown", "\n".join(lines).strip()))
        else:  # jupytext comments out IPython magics (`%config` → `# %config`)
            cells.append(("code", re.sub(r"^# (?=[%!])", "", body, flags=re.M).strip()))
    return cells


NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_source_is_paired(notebook):
    source = notebook.with_suffix(".py")
    assert source.exists(), f"{notebook.name} needs its text source {source.name} (jupytext)"
    nb = json.loads(notebook.read_text())
    stored = [(c["cell_type"], "".join(c["source"]).strip()) for c in nb["cells"]]
    assert percent_cells(source.read_text()) == stored, (
        f"{source.name} and {notebook.name} differ: run "
        f"`jupytext --to ipynb --update notebooks/{source.name}` (or --execute)"
    )
    assert nb["metadata"]["jupytext"]["formats"] == "ipynb,py:percent"


LOCAL_MODULES = {p.stem for d in ("benchmarks", "tests", "tools") for p in (ROOT / d).glob("*.py")}


@pytest.mark.parametrize("source", [p.with_suffix(".py") for p in NOTEBOOKS], ids=lambda p: p.stem)
def test_notebook_is_self_contained(source):
    """A notebook imports lievi and installed packages only, nothing from the repository's
    `benchmarks/`, `tests/` or `tools/`: a reader who has the notebook and lievi runs it."""
    text = source.read_text()
    imported = set()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Import):
            imported |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            imported.add(node.module.split(".")[0])
    assert not imported & LOCAL_MODULES, f"{source.name} imports {imported & LOCAL_MODULES}"
    assert "sys.path" not in text, f"{source.name} changes sys.path"


def test_pages_agree_on_the_test_suite_time():
    """README.md and docs/getting-started.md give the default suite's time alike."""
    said = [
        re.search(r"Run the tests \(about (\d+) minutes", (ROOT / page).read_text())
        for page in ("README.md", "docs/getting-started.md")
    ]
    assert all(said) and said[0][1] == said[1][1], [m and m[1] for m in said]
