"""Streaming access to raw files: path expansion, hashing, batched CSV reading with located errors.

Readers never hold a whole raw dataset in memory: CSV/TSV files (plain or gzip) are read in record batches
by pyarrow's streaming reader; each batch is checked and reduced before the next one is read.
"""
from __future__ import annotations

import glob
import hashlib
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.csv as pacsv

BLOCK_BYTES = 32 << 20  # pyarrow block size: ~1M rows of a Milan file per batch, bounded memory


class PrepError(ValueError):
    """Bad raw input or configuration; the message names the file, the row or key, expected and found."""


def expand_paths(patterns: Sequence[str | os.PathLike], *, root: Path | None = None) -> list[Path]:
    """Expands globs (relative to `root`) into a sorted list of existing files.

    Args:
        patterns: file paths or glob patterns.
        root: base directory for relative patterns (default: current directory).
    Returns:
        Sorted, de-duplicated list of paths.
    Raises:
        PrepError: a pattern matches no file.
    """
    out: set[Path] = set()
    for pat in patterns:
        p = Path(pat)
        if root is not None and not p.is_absolute():
            p = root / p
        hits = [h for h in sorted(glob.glob(str(p))) if Path(h).is_file()] if glob.has_magic(str(p)) \
            else ([str(p)] if p.is_file() else [])
        if not hits:
            raise PrepError(f"raw input {str(p)!r}: no such file (expected an existing file or a matching glob)")
        out.update(Path(h) for h in hits)
    return sorted(out)


def sha256_file(path: Path, chunk: int = 8 << 20) -> str:
    """Hex SHA-256 of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def describe_sources(paths: Sequence[Path]) -> list[dict]:
    """Returns [{name, bytes, sha256}] for each raw file (recorded in meta.json)."""
    return [{"name": p.name, "bytes": p.stat().st_size, "sha256": sha256_file(p)} for p in paths]


def describe_files(paths: Sequence[Path | str]) -> str:
    """The raw files read, for messages: "2 file(s) read from DIR: ['a.txt', 'b.txt']" (full paths when the
    files lie in several directories)."""
    paths = [Path(p) for p in paths]
    dirs = {p.parent for p in paths}
    if len(dirs) == 1:
        return f"{len(paths)} file(s) read from {next(iter(dirs))}: {[p.name for p in paths]}"
    return f"{len(paths)} file(s) read: {[str(p) for p in paths]}"


def check_not_empty(path: Path, expected: str) -> None:
    """A 0-byte raw file is an empty file, whatever its format (not a missing column or a corrupt archive).

    Raises:
        PrepError: naming the path and what the file should hold.
    """
    if path.is_file() and path.stat().st_size == 0:
        raise PrepError(f"{path}: empty file (0 bytes); expected {expected}")


def _open_stream(path: Path) -> pa.NativeFile:
    compression = "gzip" if path.name.endswith(".gz") else None
    return pa.input_stream(str(path), compression=compression)


def iter_csv_batches(path: Path, *, names: Sequence[str], types: dict[str, pa.DataType],
                     has_header: bool, delimiter: str = ",") -> Iterator[tuple[int, pl.DataFrame]]:
    """Streams a delimited text file (plain or .gz) as polars batches of the typed columns.

    Args:
        path: the file.
        names: without a header, the file's columns in order (the field count must match); with a header,
            the columns that must be present (any order, case/space/underscore-insensitive; extra columns
            are ignored).
        types: arrow types of the columns to return (a subset of `names`).
        has_header: the first line is a header.
        delimiter: field separator.
    Yields:
        (first_line_number, batch): 1-based line number in the file of the batch's first row, and the batch
        with the columns of `types`.
    Raises:
        PrepError: missing file, missing/renamed column, wrong field count, non-numeric field, truncated
            gzip; the message names the file and, where it can be found, the line.
    """
    column_names = _column_names(path, names, has_header, delimiter)
    read = pacsv.ReadOptions(column_names=column_names, skip_rows=1 if has_header else 0,
                             block_size=BLOCK_BYTES, use_threads=True)
    parse = pacsv.ParseOptions(delimiter=delimiter)
    # Only a blank field is null: pyarrow's default null tokens (NA, NULL, nan, N/A, ...) would turn such text
    # in a numeric column into a blank (a zero once summed), silently.
    conv = pacsv.ConvertOptions(column_types=types, include_columns=list(types), null_values=[""])
    floats = [c for c, t in types.items() if pa.types.is_floating(t)]
    line = 2 if has_header else 1
    try:
        with _open_stream(path) as stream:
            reader = pacsv.open_csv(stream, read_options=read, parse_options=parse, convert_options=conv)
            for batch in reader:
                df = pl.from_arrow(batch)
                assert isinstance(df, pl.DataFrame)
                for col in floats:  # the float parser reads nan and inf as numbers: no count is either
                    i = first_bad(~df[col].is_finite().fill_null(True))
                    if i is not None:
                        raise _not_a_number(path, line + i, col, str(df[col][i]), column_names=column_names,
                                            types=types, has_header=has_header, delimiter=delimiter)
                yield line, df
                line += batch.num_rows
    except (pa.ArrowInvalid, OSError, EOFError) as exc:
        raise _explain(path, exc, column_names=column_names, types=types, has_header=has_header,
                       delimiter=delimiter) from exc


def _norm(name: str) -> str:
    return " ".join(name.strip().lower().replace("_", " ").split())


def _column_names(path: Path, expected: Sequence[str], has_header: bool, delimiter: str) -> list[str]:
    """Column names to give the parser; checks a header for the expected columns."""
    if not path.is_file():
        raise PrepError(f"{path}: no such file")
    form = (f"a header line with the columns {list(expected)}, then one line per record" if has_header else
            f"lines of {len(expected)} fields {list(expected)}")
    check_not_empty(path, form)
    try:
        with _open_stream(path) as s:
            head = s.read(1 << 16)
    except (OSError, EOFError) as exc:
        raise _explain(path, exc, column_names=list(expected), types={}, has_header=has_header,
                       delimiter=delimiter) from exc
    if not head.strip():
        inside = "no data after gzip decompression" if path.name.endswith(".gz") else "white space only"
        raise PrepError(f"{path}: empty file ({inside}); expected {form}")
    if not has_header:
        return list(expected)
    first = head.split(b"\n", 1)[0].decode("utf-8", "replace").rstrip("\r")
    found = [_norm(n) for n in first.split(delimiter)]
    missing = [n for n in expected if _norm(n) not in found]
    if missing:
        raise PrepError(f"{path}, line 1: missing column(s) {missing}; expected {list(expected)}, "
                        f"found header {first.split(delimiter)}")
    return found


def _explain(path: Path, exc: Exception, *, column_names, types, has_header, delimiter) -> PrepError:
    """Turns a pyarrow/zlib failure into a PrepError naming the file and, if possible, the line."""
    msg = str(exc)
    if isinstance(exc, (OSError, EOFError)):
        if any(k in msg.lower() for k in ("compress", "gzip", "zlib", "inflate")):
            return PrepError(f"{path}: truncated or corrupt gzip stream ({msg}); expected a complete .gz file")
        return PrepError(f"{path}: cannot read ({msg})")
    if "Expected" in msg and "columns" in msg:
        return PrepError(f"{path}: {msg.replace('CSV parse error: ', '')} "
                         f"(expected {len(column_names)} fields per line: {list(column_names)})")
    if "conversion error" in msg:
        located = locate_bad_value(path, column_names=column_names, types=types, has_header=has_header,
                                   delimiter=delimiter)
        if located is not None:
            return PrepError(f"{path}, line {located[0]}, column {located[1]!r}: {_expected(types[located[1]])}, "
                             f"found {located[2]!r}")
    return PrepError(f"{path}: {msg}")


def _expected(typ: pa.DataType) -> str:
    return "expected an integer" if pa.types.is_integer(typ) else "expected a number"


def _not_a_number(path: Path, line: int, col: str, value: str, **read) -> PrepError:
    """A non-finite float (text such as nan, NaN, inf): names the text as written in the file."""
    located = locate_bad_value(path, **read)
    if located is not None:
        line, col, value = located
    return PrepError(f"{path}, line {line}, column {col!r}: {_expected(read['types'][col])}, found {value!r}")


def locate_bad_value(path: Path, *, column_names, types, has_header, delimiter) -> tuple[int, str, str] | None:
    """Second, diagnostic pass (only after a failure): finds the first non-numeric value of a numeric column.

    A blank field is no bad value (the readers decide what a blank means); any other text that is not a finite
    number of the column's type is, null tokens such as NA, NULL or nan included.

    Returns:
        (line number, column name, offending text as written), or None if nothing is found.
    """
    read = pacsv.ReadOptions(column_names=column_names, skip_rows=1 if has_header else 0,
                             block_size=BLOCK_BYTES)
    numeric = {n: t for n, t in types.items() if pa.types.is_integer(t) or pa.types.is_floating(t)}
    conv = pacsv.ConvertOptions(column_types={n: pa.string() for n in numeric}, include_columns=list(numeric))
    line = 2 if has_header else 1
    try:
        with _open_stream(path) as stream:
            reader = pacsv.open_csv(stream, read_options=read,
                                    parse_options=pacsv.ParseOptions(delimiter=delimiter), convert_options=conv)
            for batch in reader:
                df = pl.from_arrow(batch)
                first: tuple[int, str, str] | None = None  # the earliest bad line of the batch, any column
                for col, typ in numeric.items():
                    s = df[col]
                    value = s.cast(pl.Float64 if pa.types.is_floating(typ) else pl.Int64, strict=False)
                    number = value.is_finite() if pa.types.is_floating(typ) else value.is_not_null()
                    i = first_bad(s.is_not_null() & (s.str.strip_chars() != "") & ~number.fill_null(False))
                    if i is not None and (first is None or line + i < first[0]):
                        first = (line + i, col, str(s[i]))
                if first is not None:
                    return first
                line += batch.num_rows
    except (pa.ArrowInvalid, OSError, EOFError):
        return None
    return None


def first_bad(mask: pl.Series | np.ndarray) -> int | None:
    """Index of the first True in a boolean mask, or None."""
    arr = mask.to_numpy() if isinstance(mask, pl.Series) else mask
    if arr.dtype != bool:
        arr = arr.astype(bool)
    if not arr.any():
        return None
    return int(np.argmax(arr))
