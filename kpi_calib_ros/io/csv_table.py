"""Delimited tables as spreadsheets and instruments export them, read row by row.

The text encoding (UTF-8 with or without a byte-order mark, UTF-16 by its BOM, else
cp1252 / latin-1 with a note), the separator (``,`` ``;`` tab ``|``) and the decimal
mark (a European export writes ``;`` and ``0,365``) are detected unless given, and
:class:`TableFormat` says what was found. Every failure is a
:class:`~kpi_calib_ros.core.errors.DataError` naming the file, the line or column and
the fix. Rows are yielded one at a time: memory does not grow with the file.
"""
from __future__ import annotations

import codecs
import csv
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from kpi_calib_ros.core.errors import DataError

DELIMITERS = (',', ';', '\t', '|')
DECIMALS = ('.', ',')
_CHUNK = 1 << 20
# Bytes cp1252 leaves undefined: a file holding one is read as latin-1.
_NOT_CP1252 = bytes([0x81, 0x8D, 0x8F, 0x90, 0x9D])
_COMMA_NUMBER = re.compile(r'^\s*[-+]?\d*,\d+(?:[eE][-+]?\d+)?\s*$')
_SAMPLE_ROWS = 50


@dataclass(frozen=True)
class TableFormat:
    """How a table is written: ``encoding`` (a Python codec), ``delimiter`` and
    ``decimal`` mark; ``notes`` say what was detected rather than given."""

    encoding: str
    delimiter: str
    decimal: str
    notes: tuple[str, ...] = ()

    def describe(self) -> str:
        return (f'{self.encoding}, separator {self.delimiter!r}, decimal {self.decimal!r}'
                + (f" ({'; '.join(self.notes)})" if self.notes else ''))

    def number(self, text: str) -> float:
        """``text`` as a float (decimal mark as detected); ValueError if it is none."""
        text = text.strip()
        if self.decimal == ',':
            text = text.replace(',', '.')
        return float(text)


def detect_encoding(path: Path) -> tuple[str, str | None]:
    """The codec of ``path`` and a note when it is not plain UTF-8.

    Reads the file once in 1 MiB chunks (bounded memory).

    Raises
    ------
    DataError
        NUL bytes without a byte-order mark (UTF-16 without BOM, or not a text file).
    """
    with open(path, 'rb') as f:
        head = f.read(4)
        if head.startswith((codecs.BOM_UTF32_LE, codecs.BOM_UTF32_BE)):
            return 'utf-32', 'UTF-32 by its byte-order mark'
        if head.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
            return 'utf-16', 'UTF-16 by its byte-order mark'
        bom = head.startswith(codecs.BOM_UTF8)
        f.seek(0)
        decoder = codecs.getincrementaldecoder('utf-8')()
        offset, bad, cp1252 = 0, None, True
        while chunk := f.read(_CHUNK):
            if b'\x00' in chunk:
                raise DataError(f'{path}: byte {offset + chunk.index(0)} is NUL: UTF-16 '
                                'without a byte-order mark, or not a text table; save it as '
                                'UTF-8 (CSV UTF-8) or UTF-16 with a byte-order mark')
            if bad is None:
                try:
                    decoder.decode(chunk)
                except UnicodeDecodeError as exc:
                    bad = (offset + exc.start, chunk[exc.start])
            cp1252 = cp1252 and not any(b in chunk for b in _NOT_CP1252)
            offset += len(chunk)
        if bad is None:
            try:
                decoder.decode(b'', final=True)
            except UnicodeDecodeError:
                bad = (offset - 1, 0)
    if bad is None:
        return ('utf-8-sig', 'UTF-8 byte-order mark stripped') if bom else ('utf-8', None)
    codec = 'cp1252' if cp1252 else 'latin-1'
    return codec, (f'not UTF-8 (byte 0x{bad[1]:02x} at offset {bad[0]}): read as {codec}; '
                   'save as UTF-8 if names look wrong')


def detect_format(path: str | Path, delimiter: str | None = None,
                  decimal: str | None = None) -> TableFormat:
    """Encoding, separator and decimal mark of ``path`` (given ones are kept).

    The separator is the candidate of :data:`DELIMITERS` the header line holds most
    often; the decimal mark is ``,`` when the separator is not and a value of the first
    rows is written ``1,5``.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f'{path}: no such file')
    if delimiter is not None and delimiter not in DELIMITERS:
        raise DataError(f'{path}: delimiter {delimiter!r}: give one of {list(DELIMITERS)}')
    if decimal is not None and decimal not in DECIMALS:
        raise DataError(f"{path}: decimal {decimal!r}: give '.' or ','")
    encoding, note = detect_encoding(path)
    notes = [note] if note else []
    with open(path, newline='', encoding=encoding) as f:
        header = f.readline(1 << 17).lstrip('\ufeff')
        sample = [f.readline(1 << 17) for _ in range(_SAMPLE_ROWS)]
    if delimiter is None:
        delimiter = max(DELIMITERS, key=header.count)
        delimiter = delimiter if header.count(delimiter) else ','
        notes.append(f'separator {delimiter!r} detected')
    if decimal is None:
        comma = delimiter != ',' and any(
            _COMMA_NUMBER.match(field) for line in sample for field in line.split(delimiter))
        decimal = ',' if comma else '.'
        if comma:
            notes.append('decimal commas detected')
    if delimiter == decimal:
        raise DataError(f'{path}: separator and decimal mark are both {delimiter!r}; give '
                        "--delimiter ';' (or --decimal '.')")
    return TableFormat(encoding, delimiter, decimal, tuple(notes))


def read_table(path: str | Path, fmt: TableFormat) -> Iterator[tuple[int, dict[str, str]]]:
    """The header, then ``(line number, {column: text})`` for every data row.

    The first item is ``(1, {name: name})`` for the header (checked: no empty or
    duplicate names). Blank lines are skipped.

    Raises
    ------
    DataError
        A duplicate or empty column name, a field over the csv module's limit (an
        unbalanced quote), a row with more or fewer fields than the header.
    """
    path = Path(path)
    with open(path, newline='', encoding=fmt.encoding) as f:
        reader = csv.reader(f, delimiter=fmt.delimiter)
        rows = _checked(reader, path)
        header = next(rows, None)
        if header is None:
            raise DataError(f'{path}: empty file; a posture table needs a header line')
        names = [h.strip().lstrip('\ufeff').strip() for h in header]
        for i, name in enumerate(names):
            if not name:
                raise DataError(f'{path}: line 1, column {i + 1} has no name; name every '
                                'column in the header')
            if name in names[:i]:
                raise DataError(f'{path}: line 1: column {name!r} appears twice (columns '
                                f'{names.index(name) + 1} and {i + 1}); rename one of them')
        yield 1, {n: n for n in names}
        for row in rows:
            if not any(field.strip() for field in row):
                continue
            if len(row) != len(names):
                raise DataError(f'{path}: line {reader.line_num} has {len(row)} fields, the '
                                f'header {len(names)} (separator {fmt.delimiter!r}); give the '
                                "right --delimiter or fix the row")
            yield reader.line_num, dict(zip(names, row))


def _checked(reader: Iterator[list[str]], path: Path) -> Iterator[list[str]]:
    line = 0
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            limit = csv.field_size_limit()
            if 'field larger than field limit' in str(exc):
                raise DataError(f'{path}: after line {line}: a field longer than {limit} '
                                'characters (an unbalanced quote \'"\', or not a table); fix '
                                'the quoting of that line') from None
            raise DataError(f'{path}: after line {line}: {exc}; fix that line') from None
        except UnicodeDecodeError as exc:
            raise DataError(f'{path}: after line {line}: {exc}; save the table as UTF-8'
                            ) from None
        line = getattr(reader, 'line_num', line + 1)
        yield row


__all__ = ['DECIMALS', 'DELIMITERS', 'TableFormat', 'detect_encoding', 'detect_format',
           'read_table']
