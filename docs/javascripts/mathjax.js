// MathJax 3 configuration (the site serves MathJax itself: assets/mathjax/, see
// tools/mkdocs_math.py). Only the containers written by pymdownx.arithmatex (and, on the
// notebook pages, by tools/mkdocs_math.py) are typeset; code and prose are left alone.
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"]],
    displayMath: [["\\[", "\\]"]],
    processEscapes: true,
    processEnvironments: true,
    tags: "ams",
  },
  // SVG output: the glyphs are paths, defined once per page (no web fonts to load).
  svg: { fontCache: "global" },
  options: {
    ignoreHtmlClass: ".*|",
    processHtmlClass: "arithmatex",
  },
};

// Material's instant navigation swaps page content without a reload: typeset it again.
if (typeof document$ !== "undefined") {
  document$.subscribe(() => {
    if (window.MathJax && MathJax.typesetPromise) {
      MathJax.startup.output.clearCache();
      MathJax.typesetClear();
      MathJax.texReset();
      MathJax.typesetPromise();
    }
  });
}
