"""Whitespace tokens of mesh text, found in bulk with numpy, a chunk of lines at a time.

The text readers' fast paths see a file as lines of tokens.  :func:`chunks` cuts the text at
line breaks into pieces of about :data:`CHUNK_BYTES` (so that the per-byte work arrays stay
small whatever the file size) and :class:`Chunk` finds, in one pass over a piece, every token's
start and end, the number of tokens on each line, and where the characters that make a token
more than digits sit (``+ , - . /`` and ``e``/``E``).  Whitespace is ASCII's (space and
``\\t \\n \\v \\f \\r``); the callers turn line endings into ``\\n`` first and refuse the
control characters that could be confused with it.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from .common import BadNumber, numbers
from .numparse import PAD, parse_floats, parse_ints, word_view

__all__ = ["CHUNK_BYTES", "Chunk", "chunks", "runs"]

CHUNK_BYTES = 1 << 21


class Chunk:
    """The tokens of a run of whole lines.

    Attributes:
        buf: the lines as ``uint8``, padded with spaces (and a final ``\\n`` when missing).
        start, end: ``(T,)`` int64 byte offsets in ``buf`` of each token (end exclusive).
        per_line: ``(L,)`` int64 number of tokens on each line, blank lines included.
        line0: 0-based index of the chunk's first line in the whole text.
    """

    def __init__(self, text: bytes, begin: int, stop: int, line0: int) -> None:
        """The lines ``text[begin:stop]`` (copied once, into the padded buffer)."""
        size = stop - begin
        tail = 0 if text[stop - 1 : stop] == b"\n" else 1
        buf = np.full(PAD + size + tail + PAD, 32, dtype=np.uint8)
        buf[PAD : PAD + size] = np.frombuffer(text, dtype=np.uint8, count=size, offset=begin)
        if tail:
            buf[PAD + size] = 10
        self.buf = buf
        self.line0 = line0
        self._words: np.ndarray | None = None
        ws = buf <= 32
        change = np.zeros(len(buf), dtype=bool)  # a token starts or ends here
        np.not_equal(ws[:-1], ws[1:], out=change[1:])
        folded = buf | np.uint8(32)  # 'E' -> 'e'; + , - . / keep their codes
        special = (folded - np.uint8(43)) <= 4  # + , - . /
        special |= folded == 101  # e E
        del folded
        events = change | special
        events |= buf == 10
        ev = np.flatnonzero(events)
        del events
        # Selections below are take(flatnonzero(mask)): numpy's boolean-mask indexing is two to
        # three times slower on these sizes.
        at_change, blank = change.take(ev), ws.take(ev)
        del change, ws
        is_start = at_change & ~blank
        is_end = at_change & blank
        # the token each event is in (int32: numpy's bool -> int64 running sum is slower)
        small = np.int32 if len(buf) < 2**31 else np.int64
        token_of = np.cumsum(is_start, dtype=small) - small(1)
        self.start = ev.take(np.flatnonzero(is_start))
        self.end = ev.take(np.flatnonzero(is_end))
        chars = buf.take(ev)
        before = token_of.take(np.flatnonzero(chars == 10)) + 1  # tokens before each line break
        self.per_line = np.diff(before, prepend=0).astype(np.int64)
        keep = np.flatnonzero(special.take(ev))
        self._special_at = ev.take(keep)
        self._special_token = token_of.take(keep)
        self._special_char = chars.take(keep)

    @property
    def words(self) -> np.ndarray:
        if self._words is None:
            self._words = word_view(self.buf)
        return self._words

    @property
    def first_token(self) -> np.ndarray:
        """``(L,)`` index of each line's first token (of the next line's, for a blank one)."""
        return np.cumsum(self.per_line) - self.per_line

    def text(self, token: int) -> str:
        return self.buf[self.start[token] : self.end[token]].tobytes().decode("latin-1")

    def line_text(self, first: int, count: int) -> str:
        """The text of ``count`` tokens from token ``first`` (one line)."""
        return self.buf[self.start[first] : self.end[first + count - 1]].tobytes().decode("latin-1")

    def floats(self, tokens: np.ndarray) -> np.ndarray:
        """float64 values of ``tokens`` (indices), each exactly ``float(token)``.

        Raises:
            BadNumber: a token is no number; ``position`` is its index in ``tokens``.
        """
        if len(tokens) == 0:  # a chunk of faces only: none of the per-token work below
            return np.zeros(0, dtype=np.float64)
        t = len(self.start)
        chars, owner, at = self._special_char, self._special_token, self._special_at
        dot = np.full(t, -1, dtype=np.int64)
        exp = np.full(t, -1, dtype=np.int64)
        slow = np.zeros(t, dtype=bool)
        dot_owner = owner.take(dots := np.flatnonzero(chars == 46))
        exp_owner = owner.take(exps := np.flatnonzero((chars | np.uint8(32)) == 101))
        dot[dot_owner] = at.take(dots)
        exp[exp_owner] = at.take(exps)
        slow[owner.take(np.flatnonzero((chars == 44) | (chars == 47)))] = True
        for marks in (dot_owner, exp_owner):  # sorted: a second mark follows its token's first
            slow[marks[1:].take(np.flatnonzero(marks[1:] == marks[:-1]))] = True
        signs = np.flatnonzero((chars == 43) | (chars == 45))
        sign_at, sign_owner = at.take(signs), owner.take(signs)
        leading = sign_at == self.start.take(sign_owner)
        after_exp = (self.buf.take(sign_at - 1) | np.uint8(32)) == 101
        slow[sign_owner.take(np.flatnonzero(~(leading | after_exp)))] = True
        d, e = dot.take(tokens), exp.take(tokens)
        slow_t = slow.take(tokens)
        slow_t |= (e >= 0) & (d > e)
        values, slow_parse = parse_floats(
            self.buf, self.words, self.start.take(tokens), self.end.take(tokens), d, e
        )
        slow_t |= slow_parse
        self._exact(values, tokens, slow_t, float)
        return values

    def ints(self, tokens: np.ndarray, stop: np.ndarray | None = None) -> np.ndarray:
        """int64 values of ``tokens`` (read up to ``stop`` when given), as Python's ``int``.

        Raises:
            BadNumber: as :meth:`floats`.
        """
        end = self.end[tokens] if stop is None else stop
        values, slow = parse_ints(self.buf, self.words, self.start[tokens], end)
        if slow.any():
            where = np.flatnonzero(slow)
            text = [
                self.buf[self.start[tokens[i]] : end[i]].tobytes().decode("latin-1")
                for i in where.tolist()
            ]
            try:
                values[where] = numbers(text, int)
            except BadNumber as e:
                raise BadNumber(int(where[e.position]), e.token) from None
        return values

    def _exact(self, values: np.ndarray, tokens: np.ndarray, slow: np.ndarray, kind: type) -> None:
        """Convert the tokens the bulk path left to Python (through :func:`numbers`)."""
        if not slow.any():
            return
        where = np.flatnonzero(slow)
        text = [self.text(int(tokens[i])) for i in where.tolist()]
        try:
            values[where] = numbers(text, kind)
        except BadNumber as e:
            raise BadNumber(int(where[e.position]), e.token) from None

    def first_slash(self, tokens: np.ndarray) -> np.ndarray:
        """Offset of each token's first ``/`` (its end when it has none)."""
        stop = self.end[tokens].copy()
        slash = self._special_char == 47
        if not slash.any():
            return stop
        owner, at = self._special_token[slash], self._special_at[slash]
        first = np.ones(len(owner), dtype=bool)
        first[1:] = owner[1:] != owner[:-1]
        full = np.full(len(self.start), -1, dtype=np.int64)
        full[owner[first]] = at[first]
        mine = full[tokens]
        return np.where(mine >= 0, mine, stop)


def chunks(text: bytes, begin: int = 0) -> Iterator[Chunk]:
    """:class:`Chunk` s of ``text[begin:]``, cut after line breaks."""
    pos, line0 = begin, 0
    size = len(text)
    while pos < size:
        stop = min(pos + CHUNK_BYTES, size)
        if stop < size:
            cut = text.rfind(b"\n", pos, stop)
            if cut < 0:
                cut = text.find(b"\n", stop)
            stop = size if cut < 0 else cut + 1
        chunk = Chunk(text, pos, stop, line0)
        line0 += len(chunk.per_line)
        pos = stop
        yield chunk


def runs(first: np.ndarray, size: np.ndarray) -> np.ndarray:
    """``first[i], first[i] + 1, ..., first[i] + size[i] - 1`` for every i, concatenated (one
    ``reshape`` when all sizes are equal: all-quad or all-triangle meshes)."""
    if len(size) and (size == size[0]).all():
        return (first[:, None] + np.arange(int(size[0]))).reshape(-1)
    starts = np.cumsum(size) - size
    within = np.arange(int(size.sum())) - np.repeat(starts, size)
    return np.repeat(first, size) + within
