"""The results document (``docs/results.md``): one section per experiment, rewritten whole.

Each experiment owns the text between ``<!-- begin NAME -->`` and ``<!-- end NAME -->``
(``NAME`` is the script's name, e.g. ``bench_run``) and replaces it with the table it just
printed (``--write-docs``), so the document's figures are regenerated, never edited by hand.
Text outside the markers (titles, prose) is kept as it is.

:func:`markdown_table` formats rows as a GitHub markdown table; :func:`write_results_section`
puts a section in place.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Sequence
from pathlib import Path

from uavcal_jax.errors import DataError

__all__ = ["markdown_table", "section_markers", "write_results_section"]

_NAME = re.compile(r"[A-Za-z0-9_.-]+")


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """``header`` and ``rows`` (cells already formatted, any ``str()``-able value) as a
    markdown table, one line each, no trailing newline."""
    lines = ["| " + " | ".join(map(str, header)) + " |", "|" + " --- |" * len(header)]
    for row in rows:
        if len(row) != len(header):
            raise ValueError(f"row {row!r} has {len(row)} cells, the header {len(header)}")
        lines.append("| " + " | ".join(map(str, row)) + " |")
    return "\n".join(lines)


def section_markers(name: str) -> tuple[str, str]:
    """``(begin, end)`` markers of section ``name``; ``ValueError`` unless ``name`` is letters,
    digits, ``_``, ``.`` and ``-``."""
    if not _NAME.fullmatch(name):
        raise ValueError(f"section name {name!r}: letters, digits, '_', '.', '-' only")
    return f"<!-- begin {name} -->", f"<!-- end {name} -->"


def write_results_section(name: str, markdown: str, path: str | Path) -> Path:
    """Replace section ``name`` of the markdown file ``path`` with ``markdown``.

    The text between ``<!-- begin NAME -->`` and ``<!-- end NAME -->`` becomes ``markdown``;
    a section not yet there is appended at the end (the file is created if absent). The file
    is replaced atomically (written beside it, then renamed), so a reader never sees half a
    document; two experiments writing at the same instant can still lose one section (no
    lock), rerun it.

    Raises:
        DataError: the file holds the section's markers more than once, unpaired or out of
            order (fix the file by hand: it was edited).
        ValueError: ``name`` is not a plain name, or ``markdown`` contains the markers.
    """
    path = Path(path)
    begin, end = section_markers(name)
    if begin in markdown or end in markdown:
        raise ValueError(f"the markdown of section {name!r} contains its own markers")
    text = path.read_text(encoding="utf-8") if path.exists() else ""
    n_begin, n_end = text.count(begin), text.count(end)
    block = f"{begin}\n{markdown.strip()}\n{end}"
    if n_begin == n_end == 0:
        text = (text.rstrip("\n") + "\n\n" if text.strip() else "") + block + "\n"
    elif n_begin == n_end == 1 and text.index(begin) < text.index(end):
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        raise DataError(f"section {name!r}: {n_begin} begin and {n_end} end markers, "
                        "expected one of each, begin first", path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
