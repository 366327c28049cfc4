"""Whitespace tokens of mesh text, found with numpy a chunk of lines at a time, and their numbers.

The text readers (OBJ, OFF, ASCII PLY) see a file as lines of tokens.  :func:`chunks` cuts the
prepared text (``\\n`` line breaks, see :func:`.common.plain_text`) after line breaks into pieces
of about :data:`CHUNK_BYTES`, so that the per-byte work arrays stay small whatever the file
size, and :class:`Chunk` finds every token's byte range and the tokens of each line.
Whitespace is ASCII's (space and ``\\t \\n \\v \\f \\r``), as ``bytes.split`` has it.

Numbers are converted by pyarrow's cast of strings when it is installed (the ``fast-text``
extra: floats in a tenth of numpy's time), else by numpy's text parser (``np.fromstring(...,
sep=" ")``); both give the correctly rounded double of a decimal and the exact integer.  The
bytes from the first wanted token to the last, the other tokens among them blanked out, go to
one call.  When neither vouches for a one-to-one result (a token refused or split in two, an
integer too long for int64, ``nan(...)``, numpy's unsigned ``-nan``), Python's ``float``/``int``
convert the tokens one by one (:func:`.common.numbers`) and name the first bad one, so every
value is what ``float(token)`` or ``int(token)`` gives.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import re
from collections.abc import Iterator
from typing import Any

import numpy as np

from .common import numbers

__all__ = ["CHUNK_BYTES", "Chunk", "chunks", "runs"]

CHUNK_BYTES = 1 << 20
_SPACE = np.zeros(256, dtype=bool)
_SPACE[[9, 10, 11, 12, 13, 32]] = True
_NEGATIVE_NAN = re.compile(rb"-[nN]")
_LONGEST_INT = 18  # digits strtoll reads without clamping to the int64 range


def runs(first: np.ndarray, size: np.ndarray) -> np.ndarray:
    """``first[i], first[i] + 1, ..., first[i] + size[i] - 1`` for every i, concatenated."""
    if len(size) and (size == size[0]).all():  # one degree: a reshape
        return (first[:, None] + np.arange(int(size[0]))).reshape(-1)
    starts = np.cumsum(size) - size
    within = np.arange(int(size.sum())) - np.repeat(starts, size)
    return np.repeat(first, size) + within


class Chunk:
    """The tokens of a run of whole lines.

    Attributes:
        buf: the lines' bytes, ``(B,)`` uint8 (a view of the text).
        start, end: ``(T,)`` int64 byte offsets in ``buf`` of each token (end exclusive).
        count: ``(L,)`` int64 number of tokens on each line, blank lines included.
        first: ``(L,)`` int64 index of each line's first token.
        line0: 0-based index of the chunk's first line in the whole text.
        source: the text and the offset of the chunk in it.
    """

    def __init__(self, text: bytes, begin: int, stop: int, line0: int) -> None:
        lead = int(begin > 0 and text[begin - 1] == 10)  # the line break before, a blank
        ext = np.frombuffer(text, dtype=np.uint8, count=stop - begin + lead, offset=begin - lead)
        self.buf = ext[lead:]
        self.source = (text, begin)
        self.line0 = line0
        # below the space, text holds only whitespace and ESC (see check_text), which is none
        blank = _SPACE.take(ext) if text.find(b"\x1b", begin, stop) >= 0 else ext <= 32
        # tokens start and end where blank and non-blank bytes meet: one pass finds both
        edge = np.flatnonzero(blank[1:] != blank[:-1]) + 1 - lead
        if not lead and len(blank) and not blank[0]:  # a token at the text's start
            edge = np.concatenate([[0], edge])
        if len(edge) % 2:  # the text's last token, ending with it
            edge = np.append(edge, len(self.buf))
        self.start, self.end = edge.reshape(-1, 2).T.copy()  # contiguous, for fast takes
        breaks = np.flatnonzero(self.buf == 10)
        if len(self.buf) and self.buf[-1] != 10:  # the text's last line, without its break
            breaks = np.append(breaks, len(self.buf))
        n, w = len(self.start), len(self.start) // max(len(breaks), 1)
        # the usual layout, w tokens on every line, needs no search: no line holds fewer than w
        # (its first and last within its breaks) and the total leaves none more
        fits = w and n == w * len(breaks) and (self.start[w - 1 :: w] < breaks).all()
        if fits and (self.start[w::w] > breaks[:-1]).all():
            self.first = np.arange(0, n, w)
            self.count = np.full(len(breaks), w)
        else:
            before = np.searchsorted(self.start, breaks)  # tokens before each line's end
            self.count = np.diff(before, prepend=0)
            self.first = before - self.count

    def records(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(lines, first, count, line_no)`` of the non-blank lines: each one's chunk-relative
        index, first token, number of tokens and 1-based line number in the file."""
        lines = np.flatnonzero(self.count)
        return lines, self.first.take(lines), self.count.take(lines), self.line0 + lines + 1

    def lines(self) -> Iterator[Chunk]:
        """The chunk's lines, each a chunk of its own (to find the first of several errors)."""
        text, begin = self.source
        cuts = [0, *(np.flatnonzero(self.buf == 10) + 1).tolist(), len(self.buf)]
        for i, (a, b) in enumerate(itertools.pairwise(cuts)):
            if b > a:
                yield Chunk(text, begin + a, begin + b, self.line0 + i)

    def text(self, start: int, end: int) -> str:
        """The bytes ``buf[start:end]`` as text."""
        return self.buf[start:end].tobytes().decode("latin-1")

    def line_text(self, line: int) -> str:
        """The tokens of line ``line`` (chunk-relative), single-spaced."""
        first, count = int(self.first[line]), int(self.count[line])
        if not count:
            return ""
        return " ".join(self.text(int(self.start[first]), int(self.end[first + count - 1])).split())

    def cut(self, start: np.ndarray, end: np.ndarray, byte: int, skip: int = 0) -> np.ndarray:
        """Offset of the ``skip + 1``-th ``byte`` in each range ``[start, end)`` (ranges
        increasing and disjoint), or its ``end`` when it has fewer."""
        at = np.flatnonzero(self.buf == byte) if len(start) else start
        owner = np.searchsorted(start, at, side="right") - 1
        inside = (owner >= 0) & (at < end.take(np.maximum(owner, 0)))
        at, owner = at[inside], owner[inside]
        rank = np.arange(len(owner)) - np.searchsorted(owner, owner)  # k-th in its range
        pick = rank == skip
        stop = end.copy()
        stop[owner[pick]] = at[pick]
        return stop

    def values(
        self,
        tokens: np.ndarray,
        kind: type,
        start: np.ndarray | None = None,
        end: np.ndarray | None = None,
    ) -> np.ndarray:
        """float64 (``kind`` float) or int64 (int) values of the tokens ``tokens`` (indices,
        increasing), or of the byte ranges ``buf[start:end]`` inside them, each exactly
        ``float(text)`` or ``int(text)``.

        The bytes from the first to the last are parsed by one pyarrow or numpy call, the
        other tokens among them and the rest of each token blanked out first.

        Raises:
            BadNumber: a range holds no such number; ``position`` is its index.
        """
        dtype = np.float64 if kind is float else np.int64
        n = len(tokens)
        if n == 0:
            return np.zeros(0, dtype=dtype)
        s, e = self.start.take(tokens), self.end.take(tokens)
        a = s if start is None else start
        b = e if end is None else end
        length = b - a
        if int(length.min()) > 0 and (kind is float or int(length.max()) <= _LONGEST_INT):
            lo, hi = int(a[0]), int(b[-1])
            first, last = int(tokens[0]), int(tokens[-1])
            blank = []  # byte ranges to make spaces
            if last - first + 1 != n:  # other tokens among them
                other = np.ones(last - first + 1, dtype=bool)
                other[tokens - first] = False
                o = np.flatnonzero(other) + first
                blank.append((self.start.take(o), self.end.take(o)))
            if start is not None:  # the bytes of each token before its range
                blank.append((np.maximum(s, lo), a))
            if end is not None:  # and after it
                blank.append((b, np.minimum(e, hi)))
            piece = self.buf[lo:hi]
            if blank:
                piece = piece.copy()
                for x, y in blank:
                    cut = np.flatnonzero(y > x)
                    piece[runs(x.take(cut) - lo, y.take(cut) - x.take(cut))] = 32
            # Python's turn for "nan(...)" (no float for it) and "-nan" (numpy drops the sign);
            # numpy's for integers with an x (pyarrow reads "0x1" as 1, which Python refuses).
            # Looked for in the text (blanked tokens too, which only sends more to Python)
            text, p, q = self.source[0], self.source[1] + lo, self.source[1] + hi
            odd = kind is float and (
                text.find(b"(", p, q) >= 0
                or (text.find(b"n", p, q) >= 0 or text.find(b"N", p, q) >= 0)
                and _NEGATIVE_NAN.search(text, p, q) is not None
            )
            hexa = kind is int and (text.find(b"x", p, q) >= 0 or text.find(b"X", p, q) >= 0)
            out = None if odd or hexa else _arrow_numbers(piece, a - lo, dtype)
            if out is None and not odd:
                with contextlib.suppress(ValueError):  # numpy refuses a token (and stops there)
                    out = np.fromstring(piece.tobytes(), dtype=dtype, sep=" ")
            if out is not None and len(out) == n:  # one value per token: each read whole
                return out
        texts = [self.text(x, y) for x, y in zip(a.tolist(), b.tolist(), strict=True)]
        return numbers(texts, kind)


@functools.cache
def _arrow() -> Any:
    """pyarrow, with its compute module, when installed (the ``fast-text`` extra), or None."""
    try:
        import pyarrow.compute
    except ImportError:
        return None
    return pyarrow


def _arrow_numbers(piece: np.ndarray, at: np.ndarray, dtype: type) -> np.ndarray | None:
    """float64 or int64 ``dtype`` of the tokens of ``piece`` (``(B,)`` uint8) starting at ``at``
    (``(n,)``, each up to the next whitespace) by pyarrow's cast of strings (floats correctly
    rounded, as by ``float``); None without pyarrow or when it refuses a token ("+1", "1_0")."""
    pa = _arrow()
    if pa is None:
        return None
    offsets = np.append(at, len(piece))  # string i: token i and the whitespace after it
    strings = pa.Array.from_buffers(
        pa.large_string(), len(at), [None, pa.py_buffer(offsets), pa.py_buffer(piece)]
    )
    try:
        trimmed = pa.compute.ascii_rtrim_whitespace(strings)
        return pa.compute.cast(trimmed, pa.from_numpy_dtype(dtype)).to_numpy()
    except pa.ArrowInvalid:  # a token that is no number
        return None


def chunks(text: bytes, begin: int = 0, line0: int = 0) -> Iterator[Chunk]:
    """:class:`Chunk` s of ``text[begin:]``, cut after line breaks, from line ``line0 + 1``."""
    pos = begin
    size = len(text)
    while pos < size:
        stop = min(pos + CHUNK_BYTES, size)
        if stop < size:
            cut = text.rfind(b"\n", pos, stop)
            if cut < 0:
                cut = text.find(b"\n", stop)
            stop = size if cut < 0 else cut + 1
        chunk = Chunk(text, pos, stop, line0)
        line0 += len(chunk.count)
        pos = stop
        yield chunk
