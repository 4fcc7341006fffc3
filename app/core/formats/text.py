"""Delimited text: XYZ, CSV and TXT (one reader; the suffix only names the habit).

Layout rules:

- UTF-8 (a byte-order mark is allowed); values separated by commas, semicolons or whitespace,
  detected on the first data row. With semicolons, a decimal comma (``1,5;2,0;3,25``) is accepted.
- Blank lines and lines starting with ``#`` are skipped.
- An optional header line names the columns (``x,y,z``, ``X Y Z intensity``, CloudCompare's
  ``//X,Y,Z,R,G,B``; units in brackets such as ``x[m]`` are ignored). A header is recognised when
  one of its values is not a number. With a header, the columns named x, y, z are the
  coordinates and every other named numeric column is kept as a float64 attribute.
- Without a header, the first three numeric columns are x, y, z and other columns are ignored.
- ``nan``/``inf`` values are allowed (those rows are dropped later and counted).

The numbers are parsed by ``numpy.loadtxt`` (C parser), about 1M rows per second here.
:func:`read_text` parses the whole file at once; :func:`summarise_text` (checking uploads)
parses it a chunk of whole lines at a time, with the same checks and messages.
"""

from __future__ import annotations

import codecs
import io
import os
import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.cloud_summary import CloudSummary, FiniteBounds
from app.core.errors import PointCloudError
from app.core.formats._common import RawCloud, Source, check_point_count, loadtxt_problem
from app.core.formats.station_fields import has_station_fields

COMMENT_PREFIX = "#"
LEADING_LINES = 1000
"""Lines searched for the header and the first data row (the rest is parsed by numpy only)."""
_UNITS = re.compile(r"[\(\[\{].*?[\)\]\}]")
CHUNK_BYTES = 1024 * 1024
"""Text parsed at a time by :func:`summarise_text` (``io.StringIO`` holds it as 4 bytes a
character for ``numpy.loadtxt``; its rows take about a third of its size as float64)."""
HEAD_BYTES = 1024 * 1024
"""Least text :func:`summarise_text` searches for the header and the first data row."""
MAX_LINE_BYTES = 1024 * 1024
"""Longest line :func:`summarise_text` accepts (a row of numbers is far shorter)."""


@dataclass(frozen=True)
class TextLayout:
    """Where the data rows of a text cloud start and how they are read (from its first lines).

    Attributes
    ----------
    data_start : int
        Offset of the first data row in the decoded text.
    first_data_index : int
        Its 0-based line index (messages say line ``first_data_index + 1``).
    delimiter : str or None
        For ``numpy.loadtxt`` (None: whitespace).
    decimal_comma : bool
        Values use a decimal comma (semicolon-separated rows).
    usecols : list of int
        Columns read: x, y, z, then the attribute columns.
    attribute_names : list of str
        Names of the attribute columns, in ``usecols`` order after x, y, z.
    """

    data_start: int
    first_data_index: int
    delimiter: str | None
    decimal_comma: bool
    usecols: list[int]
    attribute_names: list[str]


def read_text(source: Source, max_points: int | None) -> RawCloud:
    """Decode a delimited-text point cloud.

    Raises
    ------
    PointCloudError
        Not UTF-8, binary content, no data rows, fewer than three numeric columns, no x/y/z
        in a header, inconsistent column counts, non-numeric values, too many rows.
    """
    raw = source.as_bytes()
    if max_points is not None:
        check_point_count(max(raw.count(b"\n") - 1, 0), max_points, "the text file (line count)")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        lines_before = raw.count(b"\n", 0, exc.start)
        raise PointCloudError(_not_utf8_message(raw, exc, 0, lines_before)) from exc
    if "\x00" in text:
        raise PointCloudError(NUL_MESSAGE)
    layout = text_layout(text)
    table = _parse_rows(text[layout.data_start :], layout, 0)
    if table.shape[0] == 0:
        raise PointCloudError(ZERO_ROWS_MESSAGE)
    points = np.ascontiguousarray(table[:, :3])
    attributes = {
        name: np.ascontiguousarray(table[:, 3 + position])
        for position, name in enumerate(layout.attribute_names)
    }
    return RawCloud(points, attributes)


NUL_MESSAGE = (
    "not a text point cloud: the content contains NUL bytes (binary data); "
    "give the right format or suffix"
)
ZERO_ROWS_MESSAGE = "zero points: the text file has no data rows"


def _not_utf8_message(raw: bytes, exc: UnicodeDecodeError, offset: int, lines_before: int) -> str:
    """The message for bytes that are not UTF-8; ``raw`` starts at file offset ``offset`` and
    ``lines_before`` newlines precede the bad byte in the file."""
    return (
        f"not UTF-8 text: byte {raw[exc.start : exc.start + 1]!r} at offset "
        f"{offset + exc.start} (line {lines_before + 1}) cannot be decoded; save the file as "
        "UTF-8 or ASCII text, or give the right format if it is binary"
    )


def text_layout(text: str) -> TextLayout:
    """Find the header, the first data row, the delimiter and the columns in the first
    :data:`LEADING_LINES` lines of ``text`` (the whole text, or its first chunk).

    Raises
    ------
    PointCloudError
        No data row, fewer than three numeric columns, a header without x, y, z or naming
        another number of columns than the first row holds.
    """
    leading = _leading_lines(text, LEADING_LINES)
    names, first_data_index = _find_header([line for _, line in leading])
    if first_data_index is None:
        if len(leading) == LEADING_LINES:
            raise PointCloudError(
                f"no data row within the first {LEADING_LINES:,} lines (only comments, blank "
                "lines or text); expected rows of x y z numbers"
            )
        raise PointCloudError(
            "zero points: the text file has no data rows"
            + (" after its header" if names else "")
            + "; expected rows of x y z numbers"
        )
    data_start, first_row = leading[first_data_index]
    first_row = first_row.strip()
    delimiter, decimal_comma = _detect_delimiter(first_row)
    first_values = _split(first_row, delimiter)
    numeric = [
        _is_number(value.replace(",", ".") if decimal_comma else value) for value in first_values
    ]

    attribute_columns: dict[str, int] = {}
    if names is not None:
        if len(names) != len(first_values):
            raise PointCloudError(
                f"the header names {len(names)} columns ({', '.join(names)}) but the first "
                f"data row (line {first_data_index + 1}) has {len(first_values)} values"
            )
        normalised = [_normalise_name(name) for name in names]
        xyz_columns = []
        for axis in ("x", "y", "z"):
            if axis not in normalised:
                raise PointCloudError(
                    f"the header line ({', '.join(names)}) has no {axis!r} column; name the "
                    "coordinate columns x, y, z or remove the header line"
                )
            xyz_columns.append(normalised.index(axis))
        for column, name in enumerate(names):
            label = name.strip().lstrip("/#").strip()
            if column in xyz_columns or not numeric[column] or not label:
                continue
            unique = label
            while unique in attribute_columns:
                unique += "_"
            attribute_columns[unique] = column
    else:
        numeric_columns = [column for column, ok in enumerate(numeric) if ok]
        if len(numeric_columns) < 3:
            raise PointCloudError(
                f"need at least 3 numeric columns (x y z) but line {first_data_index + 1} "
                f"has {len(numeric_columns)}: {first_row[:60]!r}"
            )
        xyz_columns = numeric_columns[:3]
    return TextLayout(
        data_start=data_start,
        first_data_index=first_data_index,
        delimiter=delimiter,
        decimal_comma=decimal_comma,
        usecols=[*xyz_columns, *attribute_columns.values()],
        attribute_names=list(attribute_columns),
    )


def _parse_rows(body: str, layout: TextLayout, rows_before: int) -> NDArray[np.float64]:
    """The columns ``layout.usecols`` of the data rows in ``body``, shape (rows, columns);
    ``rows_before`` data rows precede ``body`` (for the row numbers of messages)."""
    if layout.decimal_comma:
        body = body.replace(",", ".")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            return np.loadtxt(
                io.StringIO(body),
                dtype=np.float64,
                delimiter=layout.delimiter,
                comments=COMMENT_PREFIX,
                usecols=layout.usecols,
                ndmin=2,
            )
    except ValueError as exc:
        if rows_before:
            exc = ValueError(
                re.sub(
                    r"at row (\d+)",
                    lambda match: f"at row {int(match.group(1)) + rows_before}",
                    str(exc),
                )
            )
        raise PointCloudError(_describe_loadtxt_error(exc, layout.first_data_index)) from exc


class FileContent:
    """Reads pieces of a :class:`Source`: with ``pread`` from its file when it has one (the
    memory map is never touched, so the pages read do not stay in this process's memory),
    else from its buffer."""

    def __init__(self, source: Source) -> None:
        self.source = source
        self.size = source.size

    def read(self, offset: int, n_bytes: int) -> bytes:
        """Up to ``n_bytes`` bytes from ``offset`` (fewer only at the end)."""
        n_bytes = max(0, min(n_bytes, self.size - offset))
        descriptor = self.source.file_descriptor
        if descriptor is None:
            return bytes(self.source.buffer[offset : offset + n_bytes])
        pieces = []
        while n_bytes > 0:
            piece = os.pread(descriptor, n_bytes, offset)
            if not piece:
                break
            pieces.append(piece)
            offset += len(piece)
            n_bytes -= len(piece)
        return b"".join(pieces)


def line_chunks(content: FileContent, start: int, chunk_bytes: int) -> Iterator[tuple[int, bytes]]:
    """The content from ``start`` on, in pieces of about ``chunk_bytes`` that end at a newline
    (the last piece: at the end), as (offset in the content, bytes).

    A piece holds whole lines only, so it decodes on its own (a newline byte is never part of
    a multi-byte UTF-8 character) and ``numpy.loadtxt`` sees whole rows.

    Raises
    ------
    PointCloudError
        A line longer than :data:`MAX_LINE_BYTES` (not a row of numbers).
    """
    position = start
    while position < content.size:
        piece = content.read(position, max(1, chunk_bytes))
        if position + len(piece) < content.size:
            cut = piece.rfind(b"\n")
            if cut >= 0:
                piece = piece[: cut + 1]
            else:  # no newline in the piece: one long line, read on to its end
                piece += _rest_of_line(content, position + len(piece), position)
        yield position, piece
        position += len(piece)


def _rest_of_line(content: FileContent, start: int, line_start: int) -> bytes:
    """The bytes from ``start`` up to and including the next newline (to the end when there is
    none); the line that began at ``line_start`` may not pass :data:`MAX_LINE_BYTES`."""
    limit = min(content.size, line_start + MAX_LINE_BYTES)
    piece = content.read(start, limit - start)
    found = piece.find(b"\n")
    if found >= 0:
        return piece[: found + 1]
    if limit < content.size:
        raise PointCloudError(
            f"a line longer than {MAX_LINE_BYTES:,} bytes starts at offset {line_start}; "
            "expected rows of x y z numbers"
        )
    return piece


def summarise_text(
    source: Source, max_points: int | None, chunk_bytes: int | None = None
) -> CloudSummary | None:
    """What :func:`read_text` and ``PointCloud.from_array`` would make of the file, as a
    :class:`~app.core.cloud_summary.CloudSummary`, parsing about ``chunk_bytes`` of text at a
    time (default :data:`CHUNK_BYTES`): memory stays at one chunk's text and rows whatever the
    file's size.

    The same checks, in the same order, give the same errors as :func:`read_text`: a first
    pass counts the lines (``max_points``) and checks the text is UTF-8 without NUL bytes, a
    second parses the rows chunk by chunk (row numbers in messages count from the first data
    row of the file).  The header and the first data row are found in the first chunk.

    Returns
    -------
    CloudSummary or None
        None when the header names station fields (a station index or per-point origins):
        those are read whole, as :func:`read_text` does.

    Raises
    ------
    PointCloudError
        As :func:`read_text`.
    """
    chunk_bytes = CHUNK_BYTES if chunk_bytes is None else chunk_bytes
    content = FileContent(source)
    newlines = 0
    first_bad: str | None = None
    has_nul = False
    for offset, piece in line_chunks(content, 0, chunk_bytes):
        codec = "utf-8-sig" if offset == 0 else "utf-8"
        if first_bad is None:
            try:
                piece.decode(codec)
            except UnicodeDecodeError as exc:
                lines_before = newlines + piece.count(b"\n", 0, exc.start)
                first_bad = _not_utf8_message(piece, exc, offset, lines_before)
        has_nul = has_nul or b"\x00" in piece
        newlines += piece.count(b"\n")
    if max_points is not None:
        check_point_count(max(newlines - 1, 0), max_points, "the text file (line count)")
    if first_bad is not None:
        raise PointCloudError(first_bad)
    if has_nul:
        raise PointCloudError(NUL_MESSAGE)

    head_offset, head = next(line_chunks(content, 0, max(chunk_bytes, HEAD_BYTES)))
    head_text = head.decode("utf-8-sig")
    layout = text_layout(head_text)
    if has_station_fields(layout.attribute_names):
        return None
    # the byte offset of the first data row: after the newline ending the line before it
    data_start = len(codecs.BOM_UTF8) if head.startswith(codecs.BOM_UTF8) else 0
    for _ in range(layout.first_data_index):
        data_start = head.index(b"\n", data_start) + 1
    bounds = FiniteBounds()
    n_rows = 0
    for _, piece in line_chunks(content, head_offset + data_start, chunk_bytes):
        table = _parse_rows(piece.decode("utf-8"), layout, n_rows)
        if table.shape[0]:
            bounds.add(np.ascontiguousarray(table[:, :3]))
            n_rows += table.shape[0]
    if n_rows == 0:
        raise PointCloudError(ZERO_ROWS_MESSAGE)
    return bounds.summary(n_rows)


def _leading_lines(text: str, limit: int) -> list[tuple[int, str]]:
    """The first ``limit`` lines as (offset of the line in ``text``, line without newline)."""
    lines: list[tuple[int, str]] = []
    position = 0
    while position < len(text) and len(lines) < limit:
        end = text.find("\n", position)
        if end < 0:
            end = len(text)
        lines.append((position, text[position:end].rstrip("\r")))
        position = end + 1
    return lines


def _find_header(lines: list[str]) -> tuple[list[str] | None, int | None]:
    """(header names or None, index of the first data line or None), skipping blanks/comments.

    The first non-comment line is a header when it names x, y and z or holds no number at all
    (a data row with a text column such as ``p1 1.0 2.0 3.0`` is not a header). A comment line
    naming x, y and z (``# x y z``, CloudCompare's ``//X,Y,Z``) is a header too.
    """
    names: list[str] | None = None
    for index, line in enumerate(lines):
        stripped = line.strip()
        if not stripped:
            continue
        candidate = _split_header(stripped.lstrip("#/").strip())
        names_xyz = {"x", "y", "z"} <= {_normalise_name(value) for value in candidate}
        if stripped.startswith(("#", "//")):
            if names is None and names_xyz:
                names = candidate
            continue
        if names is None and (names_xyz or not any(map(_is_number, candidate))):
            names = candidate
            continue
        return names, index
    return names, None


def _split_header(line: str) -> list[str]:
    for delimiter in (",", ";", "\t"):
        if delimiter in line:
            return [value.strip() for value in line.split(delimiter)]
    return line.split()


def _detect_delimiter(row: str) -> tuple[str | None, bool]:
    """(delimiter for numpy.loadtxt, whether decimal commas are used)."""
    if ";" in row:
        return ";", "," in row
    if "," in row:
        return ",", False
    return None, False


def _split(row: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return row.split()
    return [value.strip() for value in row.split(delimiter)]


def _normalise_name(name: str) -> str:
    name = _UNITS.sub("", name).strip().lstrip("/#").strip().lower()
    return name


def _is_number(value: str) -> bool:
    try:
        float(value)
    except ValueError:
        return False
    return True


def _describe_loadtxt_error(exc: ValueError, first_data_index: int) -> str:
    message = loadtxt_problem(exc)
    where = f"data rows start at line {first_data_index + 1}"
    if "could not convert" in message:
        return (
            f"non-numeric text in the data rows: {message} ({where}); every value used must "
            "be a number"
        )
    if "columns" in message or "column index" in message:
        return (
            f"inconsistent number of columns: {message} ({where}); every row needs the same columns"
        )
    return f"malformed text point cloud: {message}"
