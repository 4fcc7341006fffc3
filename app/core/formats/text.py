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
"""

from __future__ import annotations

import io
import re

import numpy as np

from app.core.errors import PointCloudError
from app.core.formats._common import RawCloud, Source, check_point_count, loadtxt_problem

COMMENT_PREFIX = "#"
LEADING_LINES = 1000
"""Lines searched for the header and the first data row (the rest is parsed by numpy only)."""
_UNITS = re.compile(r"[\(\[\{].*?[\)\]\}]")


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
        line_number = raw.count(b"\n", 0, exc.start) + 1
        raise PointCloudError(
            f"not UTF-8 text: byte {raw[exc.start : exc.start + 1]!r} at offset {exc.start} "
            f"(line {line_number}) cannot be decoded; save the file as UTF-8 or ASCII text, "
            "or give the right format if it is binary"
        ) from exc
    if "\x00" in text:
        raise PointCloudError(
            "not a text point cloud: the content contains NUL bytes (binary data); "
            "give the right format or suffix"
        )
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

    usecols = [*xyz_columns, *attribute_columns.values()]
    body = text[data_start:]
    if decimal_comma:
        body = body.replace(",", ".")
    try:
        table = np.loadtxt(
            io.StringIO(body),
            dtype=np.float64,
            delimiter=delimiter,
            comments=COMMENT_PREFIX,
            usecols=usecols,
            ndmin=2,
        )
    except ValueError as exc:
        raise PointCloudError(_describe_loadtxt_error(exc, first_data_index)) from exc
    if table.shape[0] == 0:
        raise PointCloudError("zero points: the text file has no data rows")
    points = np.ascontiguousarray(table[:, :3])
    attributes = {
        name: np.ascontiguousarray(table[:, 3 + position])
        for position, name in enumerate(attribute_columns)
    }
    return RawCloud(points, attributes)


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
