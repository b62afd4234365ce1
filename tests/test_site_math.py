"""The site's math checks themselves: `tools/check_site_math.py` fails on TeX source a
reader would see and passes on MathJax's containers; `tools/mkdocs_math.py` puts the
notebook pages' `$…$` into those containers. (The built site is checked in `.ci/run`.)
"""

import importlib.util
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parent.parent / "tools"


def load(name):
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


check = load("check_site_math")

LOADS = (
    '<script src="../javascripts/mathjax.js"></script>'
    '<script src="../assets/mathjax/tex-svg-full.js" async></script>'
)


def page(body, scripts=LOADS):
    return f"<html><head><title>t</title></head><body>{body}{scripts}</body></html>"


@pytest.mark.parametrize(
    "body",
    [
        r"<p>the Lagrangian $L(g, \Omega) = \tfrac12 \Omega^\top I \Omega$: the potential</p>",
        r"<p>with $\Gamma = g^\top e_3$, the vertical</p>",
        r"<p>over $10^5$ steps</p>",
        r"<p>$$\dot\Pi = \Pi \times \Omega$$</p>",
        r"<p>inline \(x^2\) left as source</p>",
        r"<div>\[ D_2 L_d = 0 \]</div>",
        r"<p>$a_1 <em>b</em> c_2$</p>",  # Markdown ate part of it: still TeX to a reader
    ],
)
def test_raw_tex_fails(body):
    assert check.check_page(page(body), "x/", None)


@pytest.mark.parametrize(
    "body",
    [
        r'<p>the Lagrangian <span class="arithmatex">\(L = \tfrac12 \Omega^\top I \Omega\)</span></p>',
        r'<div class="arithmatex">\[ D_2 L_d(g_{k-1}, g_k) = 0 \tag{2.1} \]</div>',
        r"<pre><code>x = f'$\alpha$'  # code keeps its dollars</code></pre>",
        r"<p>costs <code>$\beta$</code> and 5 $ or 6 $ in prose</p>",
        "<p>no math at all</p>",
    ],
)
def test_typeset_or_code_passes(body):
    assert not check.check_page(page(body), "x/", None)


def test_math_needs_the_renderer_served_with_the_site():
    math = r'<p><span class="arithmatex">\(x\)</span></p>'
    assert check.check_page(page(math, scripts=""), "x/", None)
    cdn = '<script src="https://cdn.jsdelivr.net/npm/mathjax@3/es5/tex-mml-chtml.js"></script>'
    problems = check.check_page(page(math, scripts=LOADS + cdn), "x/", None)
    assert any("outside the site" in p for p in problems)


def test_notebook_math_is_wrapped():
    pytest.importorskip("mkdocs")
    hooks = load("mkdocs_math")
    html = (
        '<!-- Load mathjax -->\n<script src=""> </script>\n<!-- End of mathjax configuration -->'
        r"<p>the Lagrangian $L(g, \Omega) = \tfrac12 \Omega^\top I \Omega$ and "
        r"$$\Gamma_{k+1} = F_k^\top \Gamma_k$$ costs 5$ and 6$</p>"
        r"<pre><code>label=f'$\Pi_{i + 1}$'</code></pre>"
    )
    wrapped = hooks.wrap_notebook_math(html)
    assert 'src=""' not in wrapped
    assert r'<span class="arithmatex">\(L(g, \Omega) = \tfrac12 \Omega^\top I \Omega\)</span>' in (
        wrapped
    )
    assert r'<span class="arithmatex">\[\Gamma_{k+1} = F_k^\top \Gamma_k\]</span>' in wrapped
    assert "costs 5$ and 6$" in wrapped  # a dollar amount is not math
    assert r"<pre><code>label=f'$\Pi_{i + 1}$'</code></pre>" in wrapped
    assert not check.check_page(page(wrapped), "x/", None)
