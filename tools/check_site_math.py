"""Check a built site for mathematics a reader would see as TeX source.

    python tools/check_site_math.py SITE_DIR      # after `mkdocs build --site-dir SITE_DIR`

Fails (exit 1, listing page and text) when

- a page's text, outside code (`pre`, `code`, `script`, …) and outside MathJax's
  containers (`.arithmatex`, written by pymdownx.arithmatex and, on the notebook pages, by
  `tools/mkdocs_math.py`), still holds TeX: `$…\\command…$`, `$$…$$`, `\\(…\\)` or
  `\\[…\\]`;
- a page with math does not load MathJax, or loads it from elsewhere than the site itself
  (a CDN), or the site lacks MathJax's script.

It reads the static HTML, so it says nothing of whether MathJax then runs: the screenshots
of `tools/docs_screenshots.py` show that.
"""

from __future__ import annotations

import re
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import urljoin, urlparse

MATHJAX = "assets/mathjax/tex-svg-full.js"
MATHJAX_CONFIG = "javascripts/mathjax.js"
MATH_CLASS = "arithmatex"

VERBATIM = {"pre", "code", "kbd", "samp", "script", "style", "textarea", "svg", "math"}
VOID = {
    "area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source",
    "track", "wbr",
}  # fmt: skip
BLOCK = {
    "p", "div", "li", "ul", "ol", "td", "th", "tr", "table", "h1", "h2", "h3", "h4", "h5",
    "h6", "blockquote", "section", "article", "nav", "header", "footer", "dd", "dt", "br",
    "hr", "details", "summary", "figure", "figcaption",
}  # fmt: skip
CUT = "\x00"  # stands for code, a math container or a block boundary: TeX does not span it

# TeX source as a reader would see it.
RAW_TEX = [
    ("$…\\command…$", re.compile(r"\$[^$\x00]{0,400}?\\[A-Za-z]+[^$\x00]{0,400}?\$")),
    ("$…^…$ / $…_…$", re.compile(r"\$[^$\s\x00][^$\x00]{0,400}?[\^_{}][^$\x00]{0,400}?\$")),
    ("$$…$$", re.compile(r"\$\$[^\x00]+?\$\$")),
    ("\\(…\\)", re.compile(r"\\\([^\x00]*?\\\)")),
    ("\\[…\\]", re.compile(r"\\\[[^\x00]*?\\\]")),
    ("\\begin{…}", re.compile(r"\\begin\{[a-z]+\*?\}")),
]


class Page(HTMLParser):
    """The visible text of a page (outside code and math containers) and its scripts."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack: list[tuple[str, bool]] = []  # (tag, hidden: code or math inside)
        self.text: list[str] = []
        self.scripts: list[str] = []
        self.math_containers = 0

    @property
    def hidden(self) -> bool:
        return bool(self.stack) and self.stack[-1][1]

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "script" and attrs.get("src") is not None:
            self.scripts.append(attrs["src"])
        classes = (attrs.get("class") or "").split()
        is_math = MATH_CLASS in classes
        self.math_containers += is_math
        if tag in BLOCK or tag in VERBATIM or is_math:
            self.text.append(CUT)
        if tag in VOID:
            return
        self.stack.append((tag, self.hidden or tag in VERBATIM or is_math))

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag not in VOID and self.stack and self.stack[-1][0] == tag:
            self.stack.pop()

    def handle_endtag(self, tag):
        for depth in range(len(self.stack) - 1, -1, -1):  # tolerate unclosed tags
            if self.stack[depth][0] == tag:
                del self.stack[depth:]
                break
        if tag in BLOCK or tag in VERBATIM:
            self.text.append(CUT)

    def handle_data(self, data):
        self.text.append(CUT if self.hidden else data)


def raw_tex(text: str) -> list[tuple[str, str]]:
    """(kind, snippet) of every TeX source left in `text`."""
    found = []
    for kind, pattern in RAW_TEX:
        for match in pattern.finditer(text):
            found.append((kind, " ".join(match.group().split())[:120]))
    return found


def check_page(html: str, page_url: str, site: Path | None) -> list[str]:
    """Problems with one page; `page_url` is its path in the site (`theory/checks/`)."""
    parser = Page()
    parser.feed(html)
    parser.close()
    problems = [f"raw TeX ({kind}): {snippet}" for kind, snippet in raw_tex("".join(parser.text))]
    if parser.math_containers or problems:
        loaded = set()
        for src in parser.scripts:
            if urlparse(src).scheme or src.startswith("//"):
                if "mathjax" in src.lower() or "katex" in src.lower():
                    problems.append(f"loads a math renderer from outside the site: {src}")
                continue
            resolved = urlparse(urljoin("/" + page_url, src)).path.lstrip("/")
            if site is not None and not (site / resolved).is_file():
                problems.append(f"loads a script the site does not have: {src}")
            loaded.add(resolved)
        for needed in (MATHJAX_CONFIG, MATHJAX):
            if needed not in loaded:
                problems.append(f"has math but does not load /{needed}")
    return problems


def check_site(site: Path) -> list[str]:
    problems = []
    for needed in (MATHJAX, MATHJAX_CONFIG):
        if not (site / needed).is_file():
            problems.append(f"{needed}: missing from the site (MathJax is served with it)")
    pages = sorted(site.rglob("*.html"))
    if not pages:
        problems.append(f"{site}: no HTML pages (build the site first)")
    for path in pages:
        rel = path.relative_to(site)
        if rel.parts[0] == "assets":
            continue
        url = rel.as_posix().removesuffix("index.html")
        for problem in check_page(path.read_text(encoding="utf-8"), url, site):
            problems.append(f"{rel}: {problem}")
    return problems


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print(__doc__.strip().splitlines()[0], "\nusage: check_site_math.py SITE_DIR")
        return 2
    site = Path(argv[0])
    problems = check_site(site)
    pages = sum(1 for p in site.rglob("*.html") if p.relative_to(site).parts[0] != "assets")
    if problems:
        print(f"check_site_math: {len(problems)} problem(s) in {site}:")
        for problem in problems:
            print("  " + problem)
        return 1
    print(f"check_site_math: {pages} pages, no raw TeX, MathJax served with the site")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
