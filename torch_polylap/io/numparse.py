"""Decimal number tokens to int64 and correctly rounded float64, in bulk.

The text readers find their number tokens as ``(start, end)`` byte offsets into a padded
``uint8`` buffer (see :mod:`.tokens`); this module turns them into numbers with numpy operations
on whole arrays, with no Python work per token:

* digits are read eight at a time: the 8 bytes ending at a digit string's end are one
  little-endian ``uint64`` (put together from the two aligned words it straddles: numpy gathers
  aligned words several times faster than unaligned ones), checked to be digits and converted
  with three multiply-add steps (the usual "SWAR" digit trick);
* :func:`parse_plain_floats` reads the common ``[+-]digits[.digits]`` form without knowing where
  the point is: it finds the point among the first eight bytes of the token by a zero-byte
  search in one word, and leaves every other form (exponents, long integer parts) as ``slow``
  for :func:`parse_floats`, which is given the positions of the point and the exponent;
* a float's decimal significand ``w`` (at most 19 digits) and exponent ``q`` give the double
  nearest to ``w * 10**q``: by one IEEE operation when ``w <= 2**53`` and ``|q| <= 22`` (both
  operands exact, one rounding), otherwise from the high word of the product of ``w`` with the
  leading 64 bits of ``5**q``, whose error is bounded so that the products too close to a
  rounding boundary (about one in two hundred) are recognised (the first step of Lemire's
  method, "Number parsing at a gigabyte per second", 2021).

Every token these paths cannot settle exactly (more than 19 significant digits, subnormal or
overflowing results, products within the error bound of a tie, or anything but plain
``[+-]digits[.digits][e[+-]digits]`` such as ``nan``, ``inf`` or ``1_000``) is returned in a
``slow`` mask; the caller converts those few with Python's ``float``/``int`` (through
:func:`.common.numbers`), so the result is always what ``float(token)`` gives.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "Scratch",
    "decimal_to_double",
    "parse_decimal_block",
    "parse_floats",
    "parse_index_block",
    "parse_ints",
    "parse_plain_floats",
    "runs",
    "text_buffer",
    "token_marks",
    "word_view",
]

U64 = np.uint64
_ZEROS = U64(0x3030303030303030)
_ABOVE_NINE = U64(0x7676767676767676)
_HIGH_BITS = U64(0x8080808080808080)
_B = 8  # bytes per word
_ZERO = U64(48)  # '0'
EXPONENTS_IN_BULK = 512  # fewer exponent tokens in a block are left slow (Python's, faster)
PAD = 24  # bytes of padding a buffer needs before its first and after its last token

_POW10_INT = np.array([10**k for k in range(20)], dtype=U64)
_POW10_FLOAT = np.array([10.0**k for k in range(23)])


def text_buffer(size: int) -> tuple[np.ndarray, np.ndarray]:
    """``(buf, words)``: a ``uint8`` buffer of spaces, ``size`` bytes rounded up to whole
    words plus one spare word (:func:`_load` reads the word after the one holding its first
    byte), and the aligned ``uint64`` words over the same memory (``words[k]`` holds bytes
    ``8k .. 8k+7``)."""
    words = np.full(size // 8 + 2, U64(0x2020202020202020))
    return words.view(np.uint8), words


def word_view(buf: np.ndarray) -> np.ndarray:
    """The aligned ``uint64`` words of a copy of ``buf`` (for buffers not made by
    :func:`text_buffer`; the tokens must end ``PAD`` bytes before its end, as there)."""
    copy, words = text_buffer(len(buf))
    copy[: len(buf)] = buf
    return words


def runs(first: np.ndarray, size: np.ndarray) -> np.ndarray:
    """``first[i], first[i] + 1, ..., first[i] + size[i] - 1`` for every i, concatenated (one
    ``reshape`` when all sizes are equal: all-quad or all-triangle meshes)."""
    if len(size) and (size == size[0]).all():
        return (first[:, None] + np.arange(int(size[0]))).reshape(-1)
    starts = np.cumsum(size) - size
    within = np.arange(int(size.sum())) - np.repeat(starts, size)
    return np.repeat(first, size) + within


def _load(words: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Bytes ``pos .. pos+7`` of the buffer under ``words`` as little-endian ``uint64``: the low
    part of the aligned word holding byte ``pos`` and the high part of the next one."""
    q = pos >> 3
    shift = (pos & 7).view(U64)
    shift <<= U64(3)
    lo = words.take(q)
    q += 1
    hi = words.take(q)
    lo >>= shift
    np.subtract(U64(64), shift, out=shift)
    hi <<= shift  # numpy defines a shift by 64 (pos on a word boundary) as giving 0
    lo |= hi
    return lo


def _digits_word(
    words: np.ndarray, end: np.ndarray, count: np.ndarray, bad: np.ndarray
) -> np.ndarray:
    """Value of the ``count`` (0-8) bytes ending at ``end`` read as digits; a nonzero ``bad``
    word (or-ed in place) marks a non-digit among them."""
    c = np.minimum(count, 8)
    np.maximum(c, 0, out=c)
    return _swar(_load(words, end - _B), c, bad)


def _swar(x: np.ndarray, c: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """Value of the ``c`` (0-8) digits in the top bytes of the words ``x`` (changed in place);
    see :func:`_digits_word`.  In-place steps: this is the hot loop."""
    # keep the top c bytes, '0' in the others (leading zeros do not change the value); shifts
    # by 64 (c = 0) give 0 in numpy, and beat two table lookups
    low = (8 - c).view(U64)
    low <<= U64(3)
    x >>= low
    x <<= low
    np.subtract(U64(64), low, out=low)
    x |= _ZEROS >> low
    x -= _ZEROS
    # A non-digit byte leaves bit 7 set in x - '0' (a byte below '0' borrows, the lowest such
    # one from no other) or in x - '0' + 0x76 (a byte above '9'): exact as "some byte is not
    # a digit", which is all that is asked.
    t = x + _ABOVE_NINE
    t |= x
    t &= _HIGH_BITS
    bad |= t
    for shift, scale, mask in _SWAR_STEPS:
        t = x >> shift
        x *= scale
        x += t
        x &= mask
    return x


_SWAR_STEPS = (
    (U64(8), U64(10), U64(0x00FF00FF00FF00FF)),
    (U64(16), U64(100), U64(0x0000FFFF0000FFFF)),
    (U64(32), U64(10000), U64(0xFFFFFFFF)),
)


def _digits(
    buf: np.ndarray, words: np.ndarray, end: np.ndarray, count: np.ndarray, bad: np.ndarray
) -> np.ndarray:
    """Value (``uint64``) of the ``count`` (0-24) digits ending at ``end`` (see _digits_word);
    more than 19 significant digits count as ``bad``."""
    longest = int(count.max()) if len(count) else 0
    if longest <= 1:  # one digit at most (face sizes, OFF's k): one byte each
        value = buf.take(end - 1).astype(U64)
        value -= _ZERO
        value *= (count >= 1).astype(U64)
        bad |= (value > U64(9)).astype(U64)
        return value
    if 2 * np.count_nonzero(count > 8) > len(count):
        return _digits_dense(words, end, count, bad, min((longest + 7) // 8, 3))
    value = _digits_word(words, end, count, bad)
    for k in (1, 2):
        if longest <= 8 * k:
            break
        # the next eight digits only where there are more (shortest-repr files mix lengths)
        longer = np.flatnonzero(count > 8 * k)
        sub_bad = np.zeros(len(longer), dtype=U64)
        more = _digits_word(words, end.take(longer) - 8 * k, count.take(longer) - 8 * k, sub_bad)
        if k == 2:  # up to 24 digits, of which at most 19 significant: no overflow
            sub_bad |= (more >= U64(1000)).astype(U64)
        more *= _POW10_INT[8 * k]
        value[longer] += more
        bad[longer] |= sub_bad
    return value


def _digits_dense(
    words: np.ndarray, end: np.ndarray, count: np.ndarray, bad: np.ndarray, spans: int
) -> np.ndarray:
    """:func:`_digits` for ``spans`` (2-3) words of digits when most strings are that long: the
    words ending at ``end``, ``end - 8``... for every string (:func:`_word_loads`), with no
    index arrays."""
    value = np.zeros(len(end), dtype=U64)
    for k, x in enumerate(_word_loads(words, end, spans, Scratch(), "")):
        c = count - 8 * k
        np.clip(c, 0, 8, out=c)
        x = _swar(x, c, bad)
        if k == 2:  # up to 24 digits, of which at most 19 significant: no overflow
            bad |= (x >= U64(1000)).astype(U64)
        x *= _POW10_INT[8 * k]
        value += x
    return value


def parse_ints(
    buf: np.ndarray, words: np.ndarray, start: np.ndarray, end: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(values int64, slow bool)`` of the integer tokens ``buf[start:end]``: ``[+-]`` and up
    to 16 digits; anything else is marked ``slow`` (its value is then meaningless).

    All tokens are first read as plain digits (face indices seldom have a sign); only those
    that fail are read again with a sign."""
    count = end - start
    bad = np.zeros(len(start), dtype=U64)
    value = _digits(buf, words, end, count, bad).view(np.int64)
    slow = bad != 0
    slow |= count > 16
    slow |= count < 1
    if not slow.any():
        return value, slow
    again = np.flatnonzero(slow)
    first_at = start.take(again)
    first = buf.take(first_at)
    neg = first == 45  # '-'
    signed = neg | (first == 43)  # '+'
    stop = end.take(again)
    count = stop - first_at - signed
    bad = np.zeros(len(again), dtype=U64)
    signed_value = _digits(buf, words, stop, count, bad).view(np.int64)
    np.negative(signed_value, out=signed_value, where=neg)
    value[again] = signed_value
    slow[again] = (bad != 0) | (count < 1) | (count > 16)
    return value, slow


def _table() -> tuple[np.ndarray, np.ndarray]:
    """For q in [_QMIN, _QMAX]: the top word ``T`` of ``5**q * 2**-b`` truncated to 128 bits
    (``2**127 <= 5**q * 2**-b < 2**128``, so ``2**63 <= T < 2**64``), and ``b``."""
    hi, b = [], []
    for q in range(_QMIN, _QMAX + 1):
        if q >= 0:
            p = 5**q
            bits = p.bit_length()
            t = p << (128 - bits) if bits <= 128 else p >> (bits - 128)
            b.append(bits - 128)
        else:
            p = 5**-q
            n = p.bit_length() + 127
            t = (1 << n) // p  # p is odd, never a power of two: 2**127 <= t < 2**128
            b.append(-n)
        hi.append(t >> 64)  # the error bound below makes the low word unneeded
    return np.array(hi, dtype=U64), np.array(b, dtype=np.int64)


_QMIN, _QMAX = -342, 308
_T_HI, _T_EXP = _table()
_M32 = U64(0xFFFFFFFF)
_S32 = U64(32)


def _mul_hi_approx(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``floor(a * b / 2**64)`` minus 0, 1 or 2 (the carry of the dropped low cross terms)."""
    a1, a0 = a >> _S32, a & _M32
    b1, b0 = b >> _S32, b & _M32
    return a1 * b1 + ((a0 * b1) >> _S32) + ((a1 * b0) >> _S32)


def _bit_length(w: np.ndarray) -> np.ndarray:
    """Bit length of each (nonzero) ``uint64``."""
    _, e = np.frexp(w.astype(np.float64))  # may round up to the next power of two
    e = e.astype(np.int64)
    too_big = (w >> (e - 1).astype(U64)) == 0
    return e - too_big


def decimal_to_double(w: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(doubles, undecided)``: ``w * 10**q`` correctly rounded (to nearest, ties to even) for
    ``uint64`` ``w``; ``undecided`` marks the few results this path cannot guarantee
    (products too close to a rounding boundary, subnormal or overflowing results)."""
    # Clinger: w and 10**|q| are exact doubles, so one IEEE operation rounds once, correctly
    easy = w <= U64(2**53)
    easy &= q >= -22
    easy &= q <= 22
    if (q <= 0).all():  # fixed notation: one division each, the hard ones redone below
        out = w.astype(np.float64)
        out /= _POW10_FLOAT.take(np.minimum(np.negative(q), 22))
        undecided = np.zeros(len(w), dtype=bool)
        if easy.all():
            return out, undecided
        out[np.flatnonzero(~easy & (w == 0))] = 0.0  # zero stays zero whatever q
    else:
        out = np.zeros(len(w), dtype=np.float64)
        undecided = np.zeros(len(w), dtype=bool)
        simple = np.flatnonzero(easy)  # indices, not masks: numpy's mask indexing is slower
        if len(simple):
            we = w.take(simple).astype(np.float64)
            qe = q.take(simple)
            p = _POW10_FLOAT.take(np.abs(qe))
            out[simple] = np.where(qe >= 0, we * p, we / p)
    hard = np.flatnonzero(~easy & (w != 0))
    if len(hard) == 0:
        return out, undecided
    wh, qh = w.take(hard), q.take(hard)
    row = np.clip(qh, _QMIN, _QMAX) - _QMIN
    shift = 64 - _bit_length(wh)
    wn = wh << shift.astype(U64)  # 2**63 <= wn < 2**64
    # The exact product P = wn * 5**q * 2**-b lies in [2**190, 2**192) and, T being the top
    # word of 5**q * 2**-b, in [wn * T * 2**64, (wn * T + wn) * 2**64): its top word
    # floor(P / 2**128) is in [a, a + 3] (a drops up to 2 carries of the low cross terms).
    a = _mul_hi_approx(wn, _T_HI[row])
    top = a >> U64(63)  # leading bit of P: 191 (top = 1) or 190
    j = U64(10) + top  # bits of the top word below the 53-bit significand
    rem = a & ((U64(1) << j) - U64(1))
    half = U64(1) << (j - U64(1))
    # Every candidate rounds the same way unless the window [rem, rem + 4] touches half; a
    # candidate past the next multiple of 2**j rounds down to the same significand.
    down = rem + U64(4) < half
    up = rem > half
    sure = (down | up) & (top == ((a + U64(4)) >> U64(63)))
    mant = (a >> j) + up.astype(U64)
    carry = mant >> U64(53)  # rounded up to 2**53: renormalise
    mant >>= carry
    e2 = 190 + (top + carry).astype(np.int64) + _T_EXP[row] + qh - shift
    biased = e2 + 1023
    sure &= (qh >= _QMIN) & (qh <= _QMAX) & (biased >= 1) & (biased <= 2046)
    bits = (np.clip(biased, 0, 2047).astype(U64) << U64(52)) | (mant & U64(2**52 - 1))
    out[hard] = bits.view(np.float64)
    undecided[hard] = ~sure
    return out, undecided


def parse_floats(
    buf: np.ndarray,
    words: np.ndarray,
    start: np.ndarray,
    end: np.ndarray,
    dot: np.ndarray,
    exp: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``(values float64, slow bool)`` of the number tokens ``buf[start:end]``.

    ``dot`` and ``exp`` give each token's position of its ``.`` and of its ``e``/``E``, or
    ``-1`` where it has none; the caller has already marked tokens with more than one of
    either, or with a sign anywhere but first or right after the ``e``, as slow.  The bytes
    between those positions must be digits, else the token is marked ``slow`` too.
    """
    first = buf.take(start)
    neg = first == 45  # '-'
    signed = (neg | (first == 43)).astype(np.int64)
    has_exp = exp >= 0
    mant_end = np.where(has_exp, exp, end)
    has_dot = dot >= 0
    int_end = np.where(has_dot, dot, mant_end)
    n_int = int_end - start - signed
    n_frac = np.where(has_dot, mant_end - dot - 1, 0)
    ok = (n_int >= 0) & (n_frac >= 0) & (n_int + n_frac >= 1) & (n_int <= 19) & (n_frac <= 24)
    bad = np.zeros(len(start), dtype=U64)
    ipart = _digits(buf, words, int_end, n_int, bad)
    fpart = _digits(buf, words, mant_end, n_frac, bad)
    q = -n_frac
    with_exp = np.flatnonzero(has_exp)
    if len(with_exp):  # exponents: only the tokens that have one (few, in most files)
        e_at = exp.take(with_exp)
        e_end = end.take(with_exp)
        e_first = buf.take(e_at + 1)
        e_signed = (e_first == 45) | (e_first == 43)
        n_exp = e_end - e_at - 1 - e_signed
        e_bad = np.zeros(len(with_exp), dtype=U64)
        e_val = _digits_word(words, e_end, n_exp, e_bad).astype(np.int64)
        ok[with_exp] &= (n_exp <= 4) & (n_exp >= 1) & (e_bad == 0)
        q[with_exp] += np.where(e_first == 45, -e_val, e_val)
    fits = n_int + n_frac <= 19
    ok &= (bad == 0) & (fits | (ipart == 0))
    w = np.where(fits, ipart * _POW10_INT[np.clip(n_frac, 0, 19)] + fpart, fpart)
    nonzero = np.flatnonzero(ok & (w != 0))
    out = np.zeros(len(start), dtype=np.float64)
    if len(nonzero):
        out[nonzero], undecided = decimal_to_double(w[nonzero], q[nonzero])
        ok[nonzero[undecided]] = False
    np.negative(out, out=out, where=neg)
    return out, ~ok


_DOTS = U64(0x2E2E2E2E2E2E2E2E)
_ONES = U64(0x0101010101010101)
_BYTE_INDEX = U64(0x0001020304050607)  # times 2**(8j): j in the top byte


def parse_plain_floats(
    buf: np.ndarray, words: np.ndarray, start: np.ndarray, end: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(values float64, slow bool)`` of the number tokens ``buf[start:end]`` written
    ``[+-]digits[.digits]`` with the point, if any, among the eight bytes after the sign (fixed
    notation of anything below ``10**7``: what mesh writers print).  Every other token (an
    exponent, a long integer part, no number at all) is marked ``slow``, to be read by
    :func:`parse_floats`.
    """
    first = buf.take(start)
    neg = first == 45  # '-'
    signed = neg | (first == 43)  # '+'
    begin = start + signed if signed.any() else start
    length = end - begin
    head = _load(words, begin)
    # The first '.' of the head: the lowest zero byte of head ^ '........', found exactly by
    # the zero-byte test (its false positives lie above a true zero byte), then its index by
    # one multiplication of the lowest flag bit.
    found = head ^ _DOTS
    flags = found - _ONES
    np.invert(found, out=found)
    flags &= found
    flags &= _HIGH_BITS
    has_dot = flags != 0
    np.invert(flags, out=found)
    found += U64(1)
    flags &= found  # the lowest flag only
    flags >>= U64(7)
    flags *= _BYTE_INDEX
    flags >>= U64(56)
    at = flags.view(np.int64)
    has_dot &= at < length  # a '.' past the token's end is the next token's
    n_int = np.where(has_dot, at, length)
    n_frac = length - n_int
    n_frac -= has_dot
    shape_ok = has_dot | (length <= 8)
    bad = np.zeros(len(start), dtype=U64)
    # the integer part: the first n_int (at most 8) bytes of the head
    if int(n_int.max(initial=0)) <= 1:  # 0.xxx, -1.xxx: one byte each
        ipart = head & U64(0xFF)
        ipart -= _ZERO
        one = n_int == 1
        bad |= ((ipart > U64(9)) & one).view(np.uint8)
        ipart *= one
    else:
        c = np.minimum(n_int, 8)
        top = head << ((8 - c) * 8).view(U64)  # a shift by 64 gives 0
        ipart = _swar(top, c, bad)
    fpart = _digits(buf, words, end, n_frac, bad)
    total = n_int + n_frac
    ok = bad == 0
    ok &= shape_ok
    ok &= total >= 1
    ok &= n_frac <= 24
    fits = total <= 19
    ok &= fits | (ipart == 0)
    ipart *= _POW10_INT.take(np.minimum(n_frac, 19))
    ipart *= fits
    ipart += fpart
    values, undecided = decimal_to_double(ipart, np.negative(n_frac))
    ok &= ~undecided
    np.negative(values, out=values, where=neg)
    return values, ~ok


def token_marks(
    buf: np.ndarray, start: np.ndarray, end: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(dot, exp, odd)`` for :func:`parse_floats`: the position of each token's ``.`` and of
    its ``e``/``E`` (``-1``: none), and ``odd`` for tokens with two of either, a ``,`` or ``/``,
    or a sign anywhere but first or right after the ``e`` (found in the tokens' own bytes)."""
    n = len(start)
    size = end - start
    pos = runs(start, size)
    owner = np.repeat(np.arange(n), size)
    chars = buf.take(pos)
    dot = np.full(n, -1, dtype=np.int64)
    exp = np.full(n, -1, dtype=np.int64)
    odd = np.zeros(n, dtype=bool)
    for marks, out in ((chars == 46, dot), ((chars | np.uint8(32)) == 101, exp)):
        at = np.flatnonzero(marks)
        mine = owner.take(at)
        out[mine] = pos.take(at)
        odd[mine[1:].take(np.flatnonzero(mine[1:] == mine[:-1]))] = True  # a second one
    odd[owner.take(np.flatnonzero((chars == 44) | (chars == 47)))] = True
    signs = np.flatnonzero((chars == 43) | (chars == 45))
    sign_at, sign_owner = pos.take(signs), owner.take(signs)
    leading = sign_at == start.take(sign_owner)
    after_exp = (buf.take(sign_at - 1) | np.uint8(32)) == 101
    odd[sign_owner.take(np.flatnonzero(~(leading | after_exp)))] = True
    odd |= (exp >= 0) & (dot > exp)
    return dot, exp, odd


class Scratch:
    """Work arrays kept from one chunk to the next.

    A fresh numpy array of a megabyte or more is memory newly mapped by the allocator, and its
    first touch (a page fault every 4 KiB) costs more than the arithmetic done on it; the block
    parsers below write their intermediate steps into these arrays instead (``out=``).
    """

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def __call__(self, key: str, n: int, dtype: type = np.int64) -> np.ndarray:
        """An uninitialised ``(n,)`` array of ``dtype`` under the name ``key`` (the same memory
        as the previous call with that name when it was as large)."""
        a = self._arrays.get(key)
        if a is None or len(a) < n or a.dtype != dtype:
            a = np.empty(n + n // 4 + 16, dtype=dtype)
            self._arrays[key] = a
        return a[:n]


_NIBBLES = U64(0x0F0F0F0F0F0F0F0F)
_SIGNS = np.array([1.0, -1.0])
_SWAR_MUL = (
    (U64(2561), U64(8), U64(0x00FF00FF00FF00FF)),  # 10 * 2**8 + 1
    (U64(6553601), U64(16), U64(0x0000FFFF0000FFFF)),  # 100 * 2**16 + 1
    (U64(42949672960001), U64(32), None),  # 10000 * 2**32 + 1
)


def _swar_digits(x: np.ndarray, low: np.ndarray) -> np.ndarray:
    """Value of the digits in the top bytes of the words ``x`` (changed in place), the bytes
    being known to be digits, below them ``low`` (``uint64``, 0 to 64) bits to ignore (``low``
    is overwritten).

    Masking the low nibble turns digit characters into their values and clears the bits
    before the digits (leading zeros); three multiply-shift steps then merge neighbouring
    digits, pairs and quadruples (Lemire's eight-digit trick)."""
    x &= np.left_shift(_NIBBLES, low, out=low)  # a shift by 64 (no digit) gives 0
    for scale, shift, mask in _SWAR_MUL:
        x *= scale
        x >>= shift
        if mask is not None:
            x &= mask
    return x


def _long_double_ok() -> bool:
    """Whether ``np.longdouble`` is the x87 80-bit format with its 64-bit significand (stored
    in 16 little-endian bytes, significand first) and divides to that precision now."""
    info = np.finfo(np.longdouble)
    if info.nmant != 63 or np.dtype(np.longdouble).itemsize != 16 or np.little_endian is False:
        return False
    third = np.ones(1, dtype=np.longdouble) / np.longdouble(3)
    return bool(third.view(U64)[0] == U64(0xAAAAAAAAAAAAAAAB))


def _pow10_long_double() -> np.ndarray:
    """``10**k`` for k in 0..27, exact in the 64-bit significand (``5**27 < 2**64``), built
    from integers without a detour through float64."""
    fives = np.array([5**k for k in range(28)], dtype=U64).astype(np.longdouble)
    return fives * np.array([2.0**k for k in range(28)]).astype(np.longdouble)


_POW10_LD = _pow10_long_double() if _long_double_ok() else None
_MIDPOINT_BITS = U64(0x7FF)
_MIDPOINT = U64(0x400)


def _divide_exact(w: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(w / 10**k correctly rounded to float64, undecided)`` for ``uint64`` ``w`` and
    ``0 <= k <= 27``, by one 64-bit-significand division, or None where no such long double
    exists (then :func:`decimal_to_double` does it).

    ``w`` and ``10**k`` are exact long doubles, so the quotient is rounded once, to 64 bits;
    rounding that to 53 bits gives the correctly rounded double unless the 64-bit quotient
    lies exactly halfway between two doubles (a 53-bit rounding boundary strictly between the
    exact quotient and its 64-bit rounding would be a nearer 64-bit number): those few, whose
    11 dropped bits read ``10000000000``, are ``undecided``."""
    if _POW10_LD is None or not _long_double_ok():
        return None
    q = w.astype(np.longdouble)
    q /= _POW10_LD.take(k)
    undecided = (q.view(U64)[0::2] & _MIDPOINT_BITS) == _MIDPOINT
    return q.astype(np.float64), undecided


def _word_loads(
    words: np.ndarray, end: np.ndarray, spans: int, scratch: Scratch, key: str
) -> list[np.ndarray]:
    """The ``spans`` words ending at ``end``, ``end - 8``...: ``spans + 1`` gathers of aligned
    words, each shared by two neighbouring words (see :func:`_load`)."""
    n = len(end)
    base = np.right_shift(end, 3, out=scratch(key + "base", n))
    shift = np.bitwise_and(end, 7, out=scratch(key + "shift", n)).view(U64)
    shift <<= U64(3)
    back = np.subtract(U64(64), shift, out=scratch(key + "back", n, U64))
    upper = words.take(base, out=scratch(key + "w0", n, U64), mode="clip")
    out = []
    for k in range(spans):
        base -= 1
        lower = words.take(base, out=scratch(key + f"w{k + 1}", n, U64), mode="clip")
        x = np.right_shift(lower, shift, out=scratch(key + f"x{k}", n, U64))
        upper <<= back  # a shift by 64 (end on a word boundary) gives 0
        x |= upper
        out.append(x)
        upper = lower
    return out


def _block_digits(
    words: np.ndarray, end: np.ndarray, count: np.ndarray, spans: int, scratch: Scratch, key: str
) -> np.ndarray:
    """Value (``uint64``) of the ``count`` (0 to ``8 * spans``, ``spans`` <= 3) digits ending
    at ``end``, the bytes being known to be digits; a value of more than 19 digits wraps (the
    caller checks).  Work arrays are ``scratch``'s, under names starting with ``key``; the
    value is one of them."""
    n = len(end)
    # bits below the digits in the word ending 8k bytes before the end: 64 - 8 * (count - 8k),
    # clipped to 0..64
    bits = np.left_shift(count, 3, out=scratch(key + "bits", n))
    low = scratch(key + "low", n)
    value = None
    for k, x in enumerate(_word_loads(words, end, spans, scratch, key)):
        np.subtract(64 * (k + 1), bits, out=low)
        if spans > 1:
            np.clip(low, 0, 64, out=low)
        x = _swar_digits(x, low.view(U64))
        if value is None:
            value = x
        else:
            x *= _POW10_INT[8 * k]
            value += x
    assert value is not None
    return value


def parse_decimal_block(
    buf: np.ndarray, words: np.ndarray, sep: np.ndarray, out: np.ndarray, scratch: Scratch
) -> np.ndarray:
    """Values of the tokens between consecutive separators ``sep`` (``(n + 1,)`` positions of
    single blank bytes: token i is ``buf[sep[i] + 1 : sep[i + 1]]``), written into ``out``
    (``(n,)`` float64), for the tokens written ``[+-]digits[.digits]`` with at most 8 digits
    before the point and 24 after it: what mesh writers print.

    Returns the ``slow`` mask of the tokens left for :func:`parse_plain_floats` and Python
    (another form, such as an exponent; no digit at all; more than 19 significant digits; a
    quotient this path cannot round with certainty): their ``out`` is meaningless.

    The form is checked on the block's bytes as a whole, not token by token: the points are
    counted (and found by one search unless each token has one after its first digit), and
    every byte but the blanks, the points and leading signs must be a digit; the few tokens
    holding another byte are found from where those bytes are."""
    n = len(sep) - 1
    lo, hi = int(sep[0]) + 1, int(sep[-1])
    start = np.add(sep[:-1], 1, out=scratch("start", n))
    end = sep[1:]
    region = buf[lo:hi]
    slow = np.zeros(n, dtype=bool)
    first = buf.take(start, out=scratch("first", n, np.uint8), mode="clip")
    neg = np.equal(first, 45, out=scratch("neg", n, np.bool_))
    signed = np.equal(first, 43, out=scratch("signed", n, np.bool_))
    signed |= neg
    n_signed = int(np.count_nonzero(signed))
    is_dot = np.equal(region, 46, out=scratch("dots", hi - lo, np.bool_))
    n_dots = int(np.count_nonzero(is_dot))
    # one digit before each point (coordinates below 10, the usual): the points are where
    # they must be, without a search, when each token has a point there and there are no
    # others
    point = np.add(start, 1, out=scratch("point", n))
    if n_signed:
        point += signed
    if (
        n_dots != n
        or not (point < end).all()
        or not (buf.take(point, out=scratch("at_point", n, np.uint8), mode="clip") == 46).all()
    ):
        dots = np.flatnonzero(is_dot)
        dots += lo
        if n_dots == n and (dots > sep[:-1]).all() and (dots < end).all():
            point = dots
        else:  # tokens without a point (or with two): the point of those with one, by search
            owner = np.searchsorted(sep, dots) - 1
            point = end.copy()  # none: the digits end the token
            point[owner] = dots
            slow[owner[1:][owner[1:] == owner[:-1]]] = True
    digit = np.subtract(region, np.uint8(48), out=scratch("bytes", hi - lo, np.uint8))
    nondigit = np.greater(digit, np.uint8(9), out=scratch("nondigit", hi - lo, np.bool_))
    exponent = None
    if int(np.count_nonzero(nondigit)) != (n - 1) + n_dots + n_signed:
        # some token holds another byte: those tokens are slow, and read below when the
        # bytes are an exponent's ``e`` and its sign
        nondigit &= region > 32
        nondigit &= region != 46
        other = np.flatnonzero(nondigit)
        other += lo
        exponent = _exponents(buf, sep, point, other, slow)
    n_int = np.subtract(point, start, out=scratch("n_int", n))
    if n_signed:
        n_int -= signed
    n_frac = np.subtract(end, point, out=scratch("n_frac", n))
    n_frac -= 1
    np.maximum(n_frac, 0, out=n_frac)
    slow |= n_int > 8
    slow |= n_frac > 24
    if slow.any():  # meaningless lengths of slow tokens: kept in the ranges read below
        odd = np.flatnonzero(slow)
        n_int[odd] = 0
        n_frac[odd] = 0
    longest_int, longest_frac = int(n_int.max()), int(n_frac.max())
    # integer part: one byte each when no token has more (coordinates below 10)
    if longest_int <= 1:
        ipart = np.subtract(point, 1, out=scratch("at", n))
        ipart = buf.take(ipart, out=scratch("ibyte", n, np.uint8), mode="clip")
        ipart -= np.uint8(48)
        ipart = np.multiply(ipart, n_int, out=scratch("ipart", n, U64), casting="unsafe")
    else:
        ipart = _block_digits(words, point, n_int, 1, scratch, "i")
    spans = max((longest_frac + 7) // 8, 1)
    fpart = _block_digits(words, end, n_frac, spans, scratch, "f")
    total = np.add(n_int, n_frac, out=scratch("total", n))
    slow |= total == 0
    _mark_long(words, end, (ipart, n_frac, total), spans, slow, scratch)
    k = np.minimum(n_frac, 19, out=scratch("k", n))
    w = np.multiply(ipart, _POW10_INT.take(k, out=scratch("scale", n, U64), mode="clip"), out=ipart)
    w += fpart
    _divide_into(out, w, n_frac, slow, scratch)
    if n_signed:
        out *= _SIGNS.take(neg.view(np.uint8), out=scratch("div", n, np.float64), mode="clip")
    if exponent is not None and len(exponent[0]) >= EXPONENTS_IN_BULK:
        tokens, e_at = exponent
        dot = point.take(tokens)
        t_start, t_end = start.take(tokens), end.take(tokens)
        dot[dot == t_end] = -1  # no point
        out[tokens], slow[tokens] = parse_floats(buf, words, t_start, t_end, dot, e_at)
    return slow


def _mark_long(
    words: np.ndarray,
    end: np.ndarray,
    parts: tuple[np.ndarray, np.ndarray, np.ndarray],
    spans: int,
    slow: np.ndarray,
    scratch: Scratch,
) -> None:
    """For :func:`parse_decimal_block`: mark ``slow`` the tokens of more than 19 digits whose
    value this path cannot hold; ``parts``: each token's integer part, fraction digit count
    and digit count."""
    ipart, n_frac, total = parts
    # more than 19 digits: exact only when the integer part is 0 and the fraction's value is
    # below 10**19 (leading zeros), else left to Python
    long = np.flatnonzero(total > 19)
    if len(long):
        fits = ipart.take(long) == 0
        if spans == 3:
            k = np.clip(n_frac.take(long) - 16, 0, 8)
            top = _block_digits(words, end.take(long) - 16, k, 1, scratch, "t")
            fits &= top < U64(1000)
        slow[long] |= ~fits


def _divide_into(
    out: np.ndarray, w: np.ndarray, n_frac: np.ndarray, slow: np.ndarray, scratch: Scratch
) -> None:
    """For :func:`parse_decimal_block`: ``out = w / 10**n_frac`` correctly rounded, the tokens
    it cannot round with certainty marked ``slow``."""
    n = len(w)
    # w <= 2**53 and 10**k exact (k <= 22): one correctly rounded division (through int64:
    # numpy converts it to float64 faster than uint64)
    k = np.minimum(n_frac, 22, out=scratch("k", n))
    np.divide(
        w.view(np.int64),
        _POW10_FLOAT.take(k, out=scratch("div", n, np.float64), mode="clip"),
        out=out,
    )
    hard = np.greater(w, U64(2**53), out=scratch("hard", n, np.bool_))
    hard |= n_frac > 22
    hard = np.flatnonzero(hard)
    if len(hard):
        wh, kh = w.take(hard), n_frac.take(hard)
        done = _divide_exact(wh, kh)
        if done is None:
            done = decimal_to_double(wh, np.negative(kh))
        out[hard] = done[0]
        slow[hard] |= done[1]


def _exponents(
    buf: np.ndarray, sep: np.ndarray, point: np.ndarray, other: np.ndarray, slow: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For :func:`parse_decimal_block`: ``(tokens, e)``, the tokens whose bytes other than
    digits, point and leading sign (at ``other``) are one ``e``/``E`` after the point and,
    right after it, at most one sign, with the position of the ``e``; every token holding
    such a byte is marked ``slow``."""
    byte = buf.take(other)
    before = buf.take(other - 1)
    sign = (byte == 45) | (byte == 43)
    keep = ~(sign & (before <= 32))  # leading signs are no other byte
    other, byte, before, sign = other[keep], byte[keep], before[keep], sign[keep]
    owner = np.searchsorted(sep, other) - 1
    odd = slow.copy()  # two points
    slow[owner] = True
    is_e = (byte | np.uint8(32)) == 101
    after_e = sign & ((before | np.uint8(32)) == 101)
    # tokens with any other byte, or two e's, or a point after the e, are not of the form
    odd[owner[~(is_e | after_e)]] = True
    e_owner = owner[is_e]
    odd[e_owner[1:][e_owner[1:] == e_owner[:-1]]] = True
    e_at = other[is_e]
    e_point = point.take(e_owner)
    odd[e_owner[(e_point > e_at) & (e_point < sep.take(e_owner + 1))]] = True  # point after e
    good = ~odd.take(e_owner)
    return e_owner[good], e_at[good]


def parse_index_block(
    buf: np.ndarray,
    words: np.ndarray,
    sep: np.ndarray,
    width: int,
    out: np.ndarray,
    scratch: Scratch,
) -> bool:
    """Read lines of ``width`` tokens ``k i1 .. ik`` with ``k = width - 1`` (2 to 9, one digit),
    ``sep`` the ``(lines * width + 1,)`` positions of the single blanks around the tokens (as
    :func:`parse_decimal_block`): the indices, ``(lines * k,)``, written into ``out`` (int64).

    False (``out`` then unspecified) when some token is not plain digits, a ``k`` differs or an
    index has more than 16 digits: the caller then reads the lines another way."""
    n = len(sep) - 1
    lines = n // width
    lo, hi = int(sep[0]) + 1, int(sep[-1])
    region = buf[lo:hi]
    digit = np.subtract(region, np.uint8(48), out=scratch("bytes", hi - lo, np.uint8))
    nondigit = np.greater(digit, np.uint8(9), out=scratch("nondigit", hi - lo, np.bool_))
    if int(np.count_nonzero(nondigit)) != n - 1:  # only the blanks between tokens
        return False
    before = sep[:-1].reshape(lines, width)
    after = sep[1:].reshape(lines, width)
    if not (after[:, 0] - before[:, 0] == 2).all():
        return False
    if not (buf.take(after[:, 0] - 1) == 48 + width - 1).all():
        return False
    k = width - 1
    end = scratch("end", lines * k).reshape(lines, k)
    np.copyto(end, after[:, 1:])
    count = np.subtract(end, before[:, 1:], out=scratch("count", lines * k).reshape(lines, k))
    count -= 1
    longest = int(count.max()) if count.size else 0
    if longest > 16:
        return False
    spans = max((longest + 7) // 8, 1)
    values = _block_digits(words, end.reshape(-1), count.reshape(-1), spans, scratch, "f")
    out[...] = values.view(np.int64)
    return True
