"""Whitespace tokens of mesh text, found in bulk with numpy, a chunk of lines at a time.

The text readers' fast paths see a file as lines of tokens.  :func:`chunks` cuts the text at
line breaks into pieces of about :data:`CHUNK_BYTES` (so that the per-byte work arrays stay
small whatever the file size) and :class:`Chunk` finds, in one pass over a piece, every token's
start and end and the number of tokens on each line.  Whitespace is ASCII's (space and
``\\t \\n \\v \\f \\r``); the callers turn line endings into ``\\n`` first and refuse the
control characters that could be confused with it.

Numbers are converted by :mod:`.numparse`: the plain fixed-notation form first, then the
tokens it leaves (exponents, long integer parts) with the positions of their point and
exponent, then the rest (``nan``, more than 19 significant digits...) by Python, so that every
value is exactly what ``float(token)`` or ``int(token)`` gives.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TypeAlias

import numpy as np

from .common import BadNumber, numbers
from .numparse import (
    PAD,
    U64,
    Scratch,
    parse_floats,
    parse_ints,
    parse_plain_floats,
    runs,
    token_marks,
)

__all__ = ["CHUNK_BYTES", "Chunk", "chunks", "runs"]

CHUNK_BYTES = 1 << 20
PYTHON_BELOW = 512  # fewer tokens than this are converted by Python's float

Tokens: TypeAlias = np.ndarray | slice  # token indices, or a slice of consecutive tokens


class Chunk:
    """The tokens of a run of whole lines.

    Attributes:
        buf: the lines as ``uint8``, padded with spaces (and a final ``\\n`` when missing).
        words: the aligned ``uint64`` words over ``buf`` (see :func:`.numparse.text_buffer`).
        sep: ``(T + 1,)`` int64 offsets of the blank before each token and after the last
            when every blank stands alone (token i is ``buf[sep[i] + 1 : sep[i + 1]]``: the
            block parsers of :mod:`.numparse` need no ``start``/``end``), else None.
        start, end: ``(T,)`` int64 byte offsets in ``buf`` of each token (end exclusive).
        per_line: ``(L,)`` int64 number of tokens on each line, blank lines included.
        first_token: ``(L,)`` index of each line's first token (of the next line's, for a
            blank one).
        blank_lines: whether some line holds no token.
        line0: 0-based index of the chunk's first line in the whole text.
    """

    def __init__(
        self, text: bytes, begin: int, stop: int, line0: int, scratch: Scratch | None = None
    ) -> None:
        """The lines ``text[begin:stop]`` (copied once, into the padded buffer: the memory of
        ``scratch``, when given, which the next chunk made with it then overwrites)."""
        size = stop - begin
        tail = 0 if text[stop - 1 : stop] == b"\n" else 1
        body = size + tail
        if scratch is None:  # work arrays of this chunk alone
            scratch = Scratch()
        # the words of text_buffer: a spare one after the padding (see numparse._load)
        self.words = scratch("chunk", (PAD + body + PAD) // 8 + 2, U64)
        buf = self.words.view(np.uint8)
        buf[:PAD] = 32
        buf[PAD + body :] = 32
        buf[PAD : PAD + size] = np.frombuffer(text, dtype=np.uint8, count=size, offset=begin)
        if tail:
            buf[PAD + size] = 10
        self.buf = buf
        self.line0 = line0
        # Blank bytes, from the padding byte before the text (so a token starts after each);
        # tokens lie between consecutive blanks that are not neighbours.  One search over the
        # bytes, then work on the (several times fewer) blanks only.
        text_bytes = buf[PAD - 1 : PAD + body]
        blank = np.less_equal(text_bytes, 32, out=scratch("blank", body + 1, bool))
        sep = np.flatnonzero(blank)
        sep += PAD - 1
        gap = np.subtract(sep[1:], sep[:-1], out=scratch("gap", len(sep) - 1))
        if int(gap.min(initial=2)) >= 2:
            # Single blanks (what writers write): every blank ends a token, a line ends at
            # each token followed by '\n', and there is no blank line.
            self.sep: np.ndarray | None = sep
            self._start: np.ndarray | None = None  # made when asked for
            self.end = sep[1:]
            ends = buf.take(self.end, out=scratch("ends", len(self.end), np.uint8), mode="clip")
            last = np.flatnonzero(np.equal(ends, 10, out=scratch("breaks", len(ends), bool)))
            self.per_line = np.diff(last, prepend=-1)
            self.first_token = last + 1
            self.first_token -= self.per_line
            self.blank_lines = False
            return
        self.sep = None
        token = np.flatnonzero(gap >= 2)
        self._start = sep.take(token)
        self._start += 1
        token += 1
        self.end = sep.take(token)
        before = np.searchsorted(self.start, np.flatnonzero(buf == 10))
        self.per_line = np.diff(before, prepend=0)
        self.first_token = before - self.per_line
        self.blank_lines = bool((self.per_line == 0).any())

    @property
    def start(self) -> np.ndarray:
        """``(T,)`` int64 byte offsets in ``buf`` of each token."""
        if self._start is None:
            assert self.sep is not None
            self._start = self.sep[:-1] + 1
        return self._start

    def lines(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | slice]:
        """``(first token, token count, line index)`` of the lines holding tokens (the index is
        a full slice when there is no blank line)."""
        if not self.blank_lines:
            return self.first_token, self.per_line, slice(None)
        keep = np.flatnonzero(self.per_line)
        return self.first_token.take(keep), self.per_line.take(keep), keep

    def text(self, token: int) -> str:
        return self.buf[self.start[token] : self.end[token]].tobytes().decode("latin-1")

    def line_text(self, first: int, count: int) -> str:
        """The text of ``count`` tokens from token ``first`` (one line)."""
        return self.buf[self.start[first] : self.end[first + count - 1]].tobytes().decode("latin-1")

    def bounds(self, tokens: Tokens) -> tuple[np.ndarray, np.ndarray]:
        """``(start, end)`` of ``tokens``."""
        if isinstance(tokens, slice):
            return self.start[tokens], self.end[tokens]
        return self.start.take(tokens), self.end.take(tokens)

    def block(self, first: int, lines: int, width: int, skip: int) -> tuple[np.ndarray, np.ndarray]:
        """``(start, end)`` of the tokens after the first ``skip`` of ``lines`` consecutive
        lines of ``width`` tokens each, from token ``first`` (without index arrays)."""
        stop = first + lines * width

        def columns(a: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(a[first:stop].reshape(lines, width)[:, skip:]).reshape(-1)

        return columns(self.start), columns(self.end)

    def floats(self, tokens: Tokens) -> np.ndarray:
        """float64 values of ``tokens``, each exactly ``float(token)``.

        Raises:
            BadNumber: a token is no number; ``position`` is its index in ``tokens``.
        """
        return self.floats_at(*self.bounds(tokens))

    def floats_at(self, start: np.ndarray, end: np.ndarray) -> np.ndarray:
        """float64 values of the tokens ``buf[start:end]`` (see :meth:`floats`)."""
        if len(start) < PYTHON_BELOW:  # a few (slow ones left by a block): the numpy paths'
            # fixed cost of some fifty calls exceeds Python's per token
            values = np.zeros(len(start), dtype=np.float64)
            self._exact(values, start, end, np.arange(len(start)), float)
            return values
        values, slow = parse_plain_floats(self.buf, self.words, start, end)
        if not slow.any():
            return values
        again = np.flatnonzero(slow)
        s, e = start.take(again), end.take(again)
        dot, exp, odd = token_marks(self.buf, s, e)
        values[again], left = parse_floats(self.buf, self.words, s, e, dot, exp)
        left |= odd
        self._exact(values, start, end, again.take(np.flatnonzero(left)), float)
        return values

    def ints(self, tokens: Tokens) -> np.ndarray:
        """int64 values of ``tokens``, as Python's ``int``.

        Raises:
            BadNumber: as :meth:`floats`.
        """
        return self.ints_at(*self.bounds(tokens))

    def ints_at(self, start: np.ndarray, end: np.ndarray, cut: int | None = None) -> np.ndarray:
        """int64 values of the tokens ``buf[start:end]``, each read up to its first byte
        ``cut`` when given (OBJ's ``12/5/7`` corners: vertex 12); see :meth:`ints`."""
        values, slow = parse_ints(self.buf, self.words, start, end)
        if not slow.any():
            return values
        if cut is not None:
            end = self._cut(start, end, cut)
            again = np.flatnonzero(slow)
            values[again], slow[again] = parse_ints(
                self.buf, self.words, start.take(again), end.take(again)
            )
        self._exact(values, start, end, np.flatnonzero(slow), int)
        return values

    def _cut(self, start: np.ndarray, end: np.ndarray, byte: int) -> np.ndarray:
        """Offset of each token's first ``byte`` (its end when it has none); ``start`` must be
        increasing."""
        at = np.flatnonzero(self.buf == byte)
        owner = np.searchsorted(start, at, side="right") - 1
        inside = np.flatnonzero((owner >= 0) & (at < end.take(np.maximum(owner, 0))))
        at, owner = at.take(inside), owner.take(inside)
        first = np.ones(len(owner), dtype=bool)
        first[1:] = owner[1:] != owner[:-1]
        stop = end.copy()
        stop[owner[first]] = at[first]
        return stop

    def _exact(
        self, values: np.ndarray, start: np.ndarray, end: np.ndarray, where: np.ndarray, kind: type
    ) -> None:
        """Convert the tokens ``where`` that the bulk paths left, with Python (through
        :func:`numbers`)."""
        if len(where) == 0:
            return
        text = [
            self.buf[s:e].tobytes().decode("latin-1")
            for s, e in zip(start.take(where).tolist(), end.take(where).tolist(), strict=True)
        ]
        try:
            values[where] = numbers(text, kind)
        except BadNumber as e:
            raise BadNumber(int(where[e.position]), e.token) from None


def chunks(text: bytes, begin: int = 0, scratch: Scratch | None = None) -> Iterator[Chunk]:
    """:class:`Chunk` s of ``text[begin:]``, cut after line breaks (each in the memory of
    ``scratch`` when given: then a chunk is valid only until the next one is made)."""
    pos, line0 = begin, 0
    size = len(text)
    while pos < size:
        stop = min(pos + CHUNK_BYTES, size)
        if stop < size:
            cut = text.rfind(b"\n", pos, stop)
            if cut < 0:
                cut = text.find(b"\n", stop)
            stop = size if cut < 0 else cut + 1
        chunk = Chunk(text, pos, stop, line0, scratch)
        line0 += len(chunk.per_line)
        pos = stop
        yield chunk
