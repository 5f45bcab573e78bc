// MathJax 3 configuration for the site; MathJax itself is vendored next to this file
// (docs/javascripts/mathjax/, Apache-2.0, see its LICENSE) so formulas render offline.
// Markdown pages: pymdownx.arithmatex (generic) writes \( \) and \[ \].
// Notebook pages (mkdocs-jupyter, inside .jupyter-wrapper) keep the notebook's $ and $$ delimiters;
// elsewhere a dollar sign stays a dollar sign.
(function () {
  var notebook = document.querySelector(".jupyter-wrapper") !== null;
  window.MathJax = {
    tex: {
      inlineMath: notebook ? [["$", "$"], ["\\(", "\\)"]] : [["\\(", "\\)"]],
      displayMath: notebook ? [["$$", "$$"], ["\\[", "\\]"]] : [["\\[", "\\]"]],
      processEscapes: true,
      processEnvironments: true
    },
    // no speech/braille/explorer extensions: they would be fetched from a CDN
    options: { enableMenu: false }
  };
})();
