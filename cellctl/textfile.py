"""Text files the user gives (cell files, CSVs): UTF-8, and where they are not, the exact place."""

from __future__ import annotations

import codecs


class NotUtf8(ValueError):
    """A file that is not UTF-8; the message says where (the first bad byte's line, column and offset)."""


def decode_utf8(data: bytes) -> str:
    """The text of a file's bytes (a UTF-8 byte-order mark dropped, line ends made "\\n", as text mode reads)."""
    bom = len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0
    try:
        text = data[bom:].decode("utf-8")
    except UnicodeDecodeError as exc:
        bad = bom + exc.start
        line = data.count(b"\n", 0, bad) + 1
        column = bad - (data.rfind(b"\n", 0, bad) + 1) + 1
        raise NotUtf8(f"not UTF-8: byte 0x{data[bad]:02x} at line {line}, column {column} (offset {bad})") from None
    return text.replace("\r\n", "\n").replace("\r", "\n")
