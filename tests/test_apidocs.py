"""make docs: the API reference builds from the docstrings without a warning."""

from casmag.apidocs import build, modules


def test_the_api_reference_builds_for_every_module(tmp_path):
    """Without the highlighted source views (``make docs`` has them): they take half the
    build's time and read no docstring."""
    out = build(tmp_path / "api", source=False)
    assert (out / "index.html").is_file()
    pages = {p.stem for p in (out / "casmag").glob("*.html")}
    assert {m.removeprefix("casmag.") for m in modules()[1:]} <= pages
    assert "Result.load" in (out / "casmag" / "result.html").read_text()
