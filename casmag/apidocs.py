"""``python -m casmag.apidocs OUT_DIR`` (``make docs``): the API reference of every casmag
module as HTML, generated from the docstrings by pdoc, with every Python warning an error
(a docstring or signature pdoc cannot read fails the build)."""

from __future__ import annotations

import pkgutil
import sys
import warnings
from pathlib import Path

import casmag


def modules() -> list[str]:
    """casmag and each of its top-level modules and subpackages, by name (the package's
    ``__all__`` lists only the top-level entry points, so pdoc is given every module; it
    documents a subpackage's modules with it)."""
    return ["casmag", *sorted(f"casmag.{m.name}" for m in pkgutil.iter_modules(casmag.__path__))]


def build(out_dir: str | Path, source: bool = True) -> Path:
    """Write the HTML reference into out_dir (index.html, casmag.html, casmag/*.html).
    source: with each function's and class's highlighted source (half the build's time)."""
    import pdoc
    import pdoc.render

    out = Path(out_dir)
    pdoc.render.configure(show_source=source)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pdoc.pdoc(*modules(), output_directory=out)
    return out


if __name__ == "__main__":  # pragma: no cover
    if len(sys.argv) != 2:
        sys.exit("usage: python -m casmag.apidocs OUT_DIR")
    print(f"wrote {build(sys.argv[1]) / 'index.html'}")
