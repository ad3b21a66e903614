"""Line-numbered tokenising of Skeletool text files, with errors that name file, line and expectation."""

from __future__ import annotations

import math
import os
from pathlib import Path

from deliffas.io.infra.files import temp_path

__all__ = ["DynaCapFormatError", "TextLines", "read_text", "write_text_atomic"]


class DynaCapFormatError(ValueError):
    """A DynaCap/Skeletool file that does not match its format.

    The message reads ``<file>:<line>: expected …, got …`` (line 1-based; 0 when the file as a whole
    is at fault, e.g. it is missing).
    """

    def __init__(self, path: str | os.PathLike, line: int, message: str):
        self.path = str(path)
        self.line = line
        self.detail = message
        where = f"{self.path}:{line}" if line else self.path
        super().__init__(f"{where}: {message}")


def read_text(path: str | os.PathLike, what: str = "file") -> str:
    """Read a text file with universal newlines; missing files and non-text bytes become DynaCapFormatError."""
    p = Path(path)
    try:
        data = p.read_bytes() if p.is_file() else None
    except OSError as err:  # unreadable, or a name the file system rejects
        raise DynaCapFormatError(p, 0, f"{what} cannot be read ({err.strerror})") from None
    if data is None:
        raise DynaCapFormatError(p, 0, f"{what} not found")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        # Latin-1 text (e.g. names with accents) is still text; NUL or control bytes are not.
        text = data.decode("latin-1")
        if any(ord(c) < 9 or 13 < ord(c) < 32 for c in text):
            line = data[: err.start].count(b"\n") + 1
            raise DynaCapFormatError(p, line, f"expected ASCII/UTF-8 text, got binary byte 0x{data[err.start]:02x}") from None
    if "\x00" in text:
        line = text[: text.index("\x00")].count("\n") + 1
        raise DynaCapFormatError(p, line, "expected text, got a NUL byte")
    return text


def write_text_atomic(path: str | os.PathLike, text: str, crlf: bool = False) -> None:
    """Write ``text`` (with ``\\n`` line ends) to ``path`` via a temporary file and an atomic rename.

    Args:
        crlf: write CRLF line ends, which the original Skeletool C++ readers on Linux require.
    """
    p = Path(path)
    if crlf:
        text = text.replace("\r\n", "\n").replace("\n", "\r\n")
    tmp = temp_path(p)
    with open(tmp, "w", encoding="utf-8", newline="") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, p)


class TextLines:
    """Cursor over the non-empty lines of a text file, keeping 1-based line numbers for errors.

    Tokens are split on any whitespace (the Python readers' behaviour; CR, tabs and CRLF/LF mixes are
    all accepted).
    """

    def __init__(self, path: str | os.PathLike, text: str | None = None, what: str = "file"):
        self.path = Path(path)
        if text is None:
            text = read_text(path, what)
        raw = text.splitlines()
        self._lines = [(i + 1, ln.strip()) for i, ln in enumerate(raw) if ln.strip()]
        self._pos = 0
        self._last_line = len(raw)

    def error(self, message: str, line: int | None = None) -> DynaCapFormatError:
        """An error at ``line`` (default: the line last returned)."""
        if line is None:
            line = self._lines[self._pos - 1][0] if self._pos > 0 else 1
        return DynaCapFormatError(self.path, line, message)

    @property
    def remaining(self) -> int:
        return len(self._lines) - self._pos

    def at_end(self) -> bool:
        return self._pos >= len(self._lines)

    @property
    def line_no(self) -> int:
        """Line number of the line last returned."""
        return self._lines[self._pos - 1][0] if self._pos > 0 else 0

    def peek(self) -> str | None:
        return self._lines[self._pos][1] if self._pos < len(self._lines) else None

    def next(self, expected: str) -> str:
        """The next non-empty line; at end of file an error saying what was ``expected``."""
        if self._pos >= len(self._lines):
            raise DynaCapFormatError(self.path, self._last_line + 1, f"expected {expected}, got end of file")
        self._pos += 1
        return self._lines[self._pos - 1][1]

    def tokens(self, expected: str, count: int | tuple[int, ...] | None = None) -> list[str]:
        """The next line split on whitespace, checked to hold ``count`` tokens (one of them if a tuple)."""
        toks = self.next(expected).split()
        if count is not None:
            allowed = (count,) if isinstance(count, int) else count
            if len(toks) not in allowed:
                want = " or ".join(str(c) for c in allowed)
                raise self.error(f"expected {expected} ({want} tokens), got {len(toks)} tokens")
        return toks

    def header(self, accepted: tuple[str, ...]) -> str:
        """Check the first line against the accepted headers (case-sensitive, as the C++ readers)."""
        line = self.next(f"header '{accepted[0]}'")
        if line not in accepted:
            raise self.error(f"expected header '{accepted[0]}', got '{line[:80]}'")
        return line

    def count(self, keyword: str, limit: int | None = None) -> int:
        """Parse a ``<keyword> N`` count line, checking N against the lines that remain."""
        toks = self.tokens(f"'{keyword} N'")
        if len(toks) != 2 or toks[0] != keyword:
            raise self.error(f"expected '{keyword} N', got '{' '.join(toks)[:80]}'")
        n = self.to_int(toks[1], f"{keyword} count")
        if n < 0:
            raise self.error(f"expected a non-negative {keyword} count, got {n}")
        if limit is not None and n > limit:
            raise self.error(f"{keyword} count {n} exceeds the {limit} lines left in the file")
        return n

    def to_int(self, token: str, what: str) -> int:
        try:
            value = int(token)
        except ValueError:
            raise self.error(f"expected an integer {what}, got '{token[:40]}'") from None
        if not -(2**31) <= value < 2**31:
            raise self.error(f"expected a 32-bit integer {what}, got '{token[:40]}'")
        return value

    def to_float(self, token: str, what: str) -> float:
        try:
            value = float(token)
        except ValueError:
            raise self.error(f"expected a number for {what}, got '{token[:40]}'") from None
        if not math.isfinite(value):
            raise self.error(f"expected a finite number for {what}, got '{token[:40]}'")
        return value

    def floats(self, tokens: list[str], what: str) -> list[float]:
        return [self.to_float(t, what) for t in tokens]
