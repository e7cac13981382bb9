"""What the command line and its input files say, checked: KEY=VALUE pairs, sizes, CSV files."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

# columns that say what a row is; not every kind fills every column (grid dots have no x_mm, a reference
# row has no angle_deg)
ROW_KINDS = ("set", "kind")


class InputError(Exception):
    """Bad input from the command line or a file: exit status 2."""


def parse_params(pairs: list[str], flag: str = "--param") -> dict:
    """KEY=VALUE pairs, each value read as YAML (so 8 is a number, true a bool, [1, 2] a list)."""
    import yaml

    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise InputError(f"{flag} {pair!r}: expected KEY=VALUE, e.g. {flag} rows=8")
        out[key.strip()] = yaml.safe_load(value) if value.strip() else ""
    return out


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--image-size {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 2448x2050") from None
    if w <= 0 or h <= 0:
        raise InputError(f"--image-size {text!r}: width and height must be positive")
    return w, h


def read_text(path: str | Path, what: str) -> str:
    """A UTF-8 text file's content; InputError naming the file, and where and why it cannot be read."""
    from cellctl.textfile import NotUtf8, decode_utf8

    try:
        return decode_utf8(Path(path).read_bytes())
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except NotUtf8 as exc:
        raise InputError(f"{path}: {exc}: save the {what} as UTF-8") from None


def read_csv(path: str, required: tuple[str, ...], numeric: tuple[str, ...]) -> list[dict]:
    """Rows of a CSV file with the `required` columns; the `numeric` ones must be finite numbers."""
    from cellctl.stores.run_folder import read_samples_text

    text = read_text(path, "CSV")
    header = next(csv.reader(io.StringIO(text)), None)
    if not header:
        raise InputError(f"{path}: empty file; expected a header with columns {', '.join(required)}")
    missing = [c for c in required if c not in [h.strip() for h in header]]
    if missing:
        raise InputError(f"{path}: missing column(s) {', '.join(missing)}; required: {', '.join(required)}"
                         f" (found: {', '.join(header)})")
    rows = read_samples_text(text)
    if not rows:
        raise InputError(f"{path}: no data rows")
    for i, row in enumerate(rows):
        measured = row.get("status") in (None, "ok")  # rows marked unmeasured may carry nan
        for col in numeric:
            value = row.get(col)
            if value is None and any(k in row for k in ROW_KINDS):  # a row of a kind that does not measure it
                continue
            if not isinstance(value, (int, float)) or (measured and not math.isfinite(value)):
                raise InputError(f"{path}: row {i + 2}, column {col}: {value!r} is not a finite number")
            row[col] = float(value)
    return rows
