"""The results document's section writer: replace, create, atomic, other sections untouched."""

from __future__ import annotations

import os

import pytest

from uavcal_jax.data.results_doc import markdown_table, write_results_section
from uavcal_jax.errors import DataError

DOC = """# Results

Prose kept as it is.

<!-- begin a -->
old a
<!-- end a -->

Between the sections.

<!-- begin b -->
| x |
| --- |
| 1 |
<!-- end b -->
"""


def test_replace_keeps_everything_else(tmp_path):
    path = tmp_path / "results.md"
    path.write_text(DOC)
    write_results_section("a", "new a\nline 2\n", path)
    expected = DOC.replace("old a", "new a\nline 2")
    assert path.read_text() == expected
    write_results_section("a", "new a\nline 2", path)  # idempotent
    assert path.read_text() == expected


def test_create_section_and_file(tmp_path):
    path = tmp_path / "docs" / "results.md"
    write_results_section("bench_run", "| t |\n| --- |\n| 1 |", path)
    assert path.read_text() == "<!-- begin bench_run -->\n| t |\n| --- |\n| 1 |\n" \
                               "<!-- end bench_run -->\n"
    path.write_text(DOC)
    write_results_section("c", "text c", path)
    assert path.read_text() == DOC + "\n<!-- begin c -->\ntext c\n<!-- end c -->\n"


def test_atomic_no_partial_file_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "results.md"
    path.write_text(DOC)

    def fail(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_results_section("a", "new a", path)
    assert path.read_text() == DOC
    assert [p.name for p in tmp_path.iterdir()] == ["results.md"]  # no temporary left


@pytest.mark.parametrize(("name", "text"), [("a", DOC + "<!-- begin a -->\n"),
                                            ("b", DOC.replace("<!-- end b -->", "")),
                                            ("a", "<!-- end a -->\n<!-- begin a -->\n")])
def test_broken_markers_name_the_file(tmp_path, name, text):
    path = tmp_path / "results.md"
    path.write_text(text)
    with pytest.raises(DataError, match=f"results.md: section '{name}'"):
        write_results_section(name, "x", path)
    assert path.read_text() == text


def test_bad_name_or_markers_in_markdown(tmp_path):
    with pytest.raises(ValueError, match="section name"):
        write_results_section("a b", "x", tmp_path / "r.md")
    with pytest.raises(ValueError, match="its own markers"):
        write_results_section("a", "<!-- end a -->", tmp_path / "r.md")


def test_markdown_table():
    assert markdown_table(("a", "b"), [(1, "x"), (2.5, "y")]) == (
        "| a | b |\n| --- | --- |\n| 1 | x |\n| 2.5 | y |")
    with pytest.raises(ValueError, match="2 cells, the header 1"):
        markdown_table(("a",), [(1, 2)])
