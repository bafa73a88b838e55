"""Reading a small text file the user gave (a tally, a weld list) with a one-line error."""

from __future__ import annotations

import os


def read_text(path: str | os.PathLike[str]) -> str:
    """A UTF-8 text file's content (a byte-order mark dropped); ValueError naming the file when
    it cannot be read or is not text."""
    p = os.fspath(path)
    try:
        with open(p, newline="", encoding="utf-8-sig") as f:
            return f.read()
    except OSError as exc:
        raise ValueError(f"{p}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{p}: not a UTF-8 text file") from None
