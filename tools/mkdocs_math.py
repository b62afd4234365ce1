"""MkDocs hooks (`hooks:` in mkdocs.yml): typeset mathematics, served with the site.

- MathJax 3 is copied into the built site (`assets/mathjax/`) from the Python package
  `django-static-mathjax` (the `docs` extra; it ships MathJax's own release files under
  the Apache-2.0 licence), so the site needs no CDN and works offline, and CI needs
  nothing beyond `pip install -e ".[docs]"`.
- Markdown pages get their math from `pymdownx.arithmatex` (generic mode), which wraps
  `$…$`, `$$…$$`, `\\(…\\)`, `\\[…\\]` in `<span|div class="arithmatex">`. The notebook
  pages (mkdocs-jupyter, through nbconvert) keep `$…$` as plain text: `on_page_content`
  wraps it in the same containers, so MathJax (configured in
  `docs/javascripts/mathjax.js` to look only inside `.arithmatex`) typesets both alike,
  and `tools/check_site_math.py` checks both alike.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.structure.files import File

# What the site serves: the combined TeX-input / SVG-output component (every TeX extension
# included, so nothing is loaded on demand; SVG output draws the glyphs itself, so there
# are no web fonts to fetch) and the licence.
MATHJAX_DEST = "assets/mathjax"
MATHJAX_FILES = ("tex-svg-full.js",)


def mathjax_root() -> Path:
    """MathJax's release files (`es5/`) as installed by django-static-mathjax."""
    try:
        import mathjax  # the import name of the `django-static-mathjax` distribution
    except ImportError as error:  # pragma: no cover - a set-up error, said plainly
        raise SystemExit(
            'MathJax is missing: pip install -e ".[docs]" (django-static-mathjax)'
        ) from error
    root = Path(mathjax.__file__).parent / "static" / "mathjax"
    if not (root / "es5" / MATHJAX_FILES[0]).is_file():  # pragma: no cover
        raise SystemExit(f"MathJax's {MATHJAX_FILES[0]} is not under {root / 'es5'}")
    return root


def on_files(files, config):
    root = mathjax_root()
    sources = [(root / "LICENSE", "LICENSE")]
    for pattern in MATHJAX_FILES:
        for path in sorted((root / "es5").glob(pattern)):
            sources.append((path, path.relative_to(root / "es5").as_posix()))
    for path, rel in sources:
        files.append(File.generated(config, f"{MATHJAX_DEST}/{rel}", abs_src_path=str(path)))
    return files


# ---- notebook pages ---------------------------------------------------------------------

# nbconvert's page carries a MathJax 2 loader (`<script src="">` when no URL is configured,
# which fetches the page itself as a script) and its configuration: replaced by the site's.
_NBCONVERT_MATHJAX = re.compile(
    r"<!-- Load mathjax -->.*?<!-- End of mathjax configuration -->", re.S
)
# Text that is code or markup stays as it is.
_VERBATIM = re.compile(r"(<(pre|code|script|style|textarea)\b.*?</\2\s*>)", re.S | re.I)
_TAG = re.compile(r"(<[^>]*>)")
# nbconvert's Markdown renderer leaves math verbatim (HTML-escaped) between its delimiters.
_DISPLAY = re.compile(r"\$\$(.+?)\$\$", re.S)
# Pandoc's rule: `$` opens when not followed by a space, closes when not preceded by one
# nor followed by a digit.
_INLINE = re.compile(r"(?<![\\$])\$(?=[^\s$])((?:[^$\\]|\\.)+?)(?<=\S)\$(?![\d$])", re.S)


def wrap_notebook_math(html: str) -> str:
    """Put the `$…$` and `$$…$$` of rendered notebook Markdown into MathJax's containers."""
    html = _NBCONVERT_MATHJAX.sub("", html)
    parts = _VERBATIM.split(html)
    out = []
    # re.split with two groups yields: text, whole verbatim block, tag name, text, …
    for index in range(0, len(parts), 3):
        pieces = _TAG.split(parts[index])
        for j in range(0, len(pieces), 2):  # text between tags
            text = _DISPLAY.sub(r'<span class="arithmatex">\\[\1\\]</span>', pieces[j])
            pieces[j] = _INLINE.sub(r'<span class="arithmatex">\\(\1\\)</span>', text)
        out.append("".join(pieces))
        if index + 1 < len(parts):
            out.append(parts[index + 1])
    return "".join(out)


def _wrap_toc(items) -> None:
    for item in items:  # the theme renders the titles as HTML, unescaped
        item.title = wrap_notebook_math(item.title)
        _wrap_toc(item.children)


def on_page_content(html, page, config, files):
    if page.file.src_uri.endswith(".ipynb"):
        _wrap_toc(page.toc)  # mkdocs-jupyter takes the headings from the raw Markdown
        return wrap_notebook_math(html)
    return html
