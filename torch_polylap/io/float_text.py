"""Doubles as the shortest decimal text that reads back exactly, in bulk.

The text writers print millions of coordinates; Python's ``repr`` of each (the shortest
round-trip decimal) costs about a microsecond a number.  This module gives the same text with
numpy operations on whole arrays:

* short decimals (at most 15 significant digits, as files written with few digits hold):
  ``s``, ``|x| * 10**(14 - e)`` rounded to an integer in double arithmetic (``e`` the decimal
  exponent, ``10**(14 - e)`` an exact double), is the only candidate, and one division
  ``s / 10**(14 - e)`` settles exactly whether it reads back as ``x`` (both operands are
  exact, so the quotient is the correctly rounded decimal);
* 16 and 17 digits with ``-6 <= e <= 14``: Dekker's product with the exact ``10**(15 - e)``
  and ``10**(16 - e)`` gives the nearest 16- and 17-digit significands exactly; the 16-digit
  one (a double below ``2**53``) is checked by one division as above; where it fails, the
  nearest 17-digit decimal is ``repr``'s and reads back as ``x`` by arithmetic alone (it is
  within ``5e-17 * |x|``, half the spacing of doubles at least ``2**-54 * |x|``);
* the others: ``|x|`` scaled by ``10**k`` (a double-double power of ten and Dekker's exact
  product: about 106 correct bits) gives the integer part and fraction of
  ``|x| * 10**(16 - e)``; from them the 17-, 16- and 15-digit significands rounded to nearest
  (ties to even), and the shortest one whose distance to ``|x|`` is within half the spacing
  of doubles there is chosen, then parsed back with the readers' exact decimal-to-double
  conversion (:func:`.numparse.decimal_to_double`; Python's ``float`` for the few it leaves
  undecided): it must give ``x`` again, else Python's ``repr`` prints that number, as it does
  ``nan``, infinities, subnormals and magnitudes beyond ``1e290``.  The exact round trip is
  thus guaranteed by a check, or for the 17-digit decimals above by their exact rounding,
  not by approximate arithmetic;
* text: the digits four at a time from a table of ASCII, the decimal point put in with byte
  masks and shifts, laid out as ``repr`` does (positional for exponents ``-4 <= e < 16``,
  else ``d.ddde+XX``) in fixed 32-byte records, every piece at a fixed place (the lead
  ``-0.000``, the digits, the exponent, the separator) with zero bytes in between, which are
  then dropped: the file's text has none.

``np.where`` is avoided in favour of blends (``b + m * (a - b)``): it costs several numpy
passes' worth of time per call.

The text is ``repr``'s (the shortest round-trip decimal, the nearest among those) except in
rare cases, where a longer decimal, still exact, is written: a shorter one exactly half a
spacing of doubles away from ``|x| >= 1e17`` (where the inexact ``10**k``, ``k < 0``, blurs
the tie) or on the short side of a power of two (whose rounding interval is lopsided).
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from .numparse import decimal_to_double

__all__ = ["ascii8", "float_lines", "float_pieces", "without_zero_bytes"]

U64 = np.uint64
_CHUNK_ROWS = 1 << 15  # lines per chunk: temporaries of a few megabytes, not of the whole mesh
_FAST_MIN, _FAST_MAX = 1e-290, 1e290  # |x| the vectorised path handles
_KMIN, _KMAX = -290, 308  # powers of ten it scales by
_POW10_INT = np.array([10**k for k in range(19)], dtype=np.int64)
_POW10_FLOAT = np.array([float(10**k) for k in range(23)])  # the exact ones


def _split26(h: float) -> tuple[float, float]:
    """``h = hi + lo`` with ``hi`` the top 26 bits of the significand (exact, no overflow)."""
    m, e = np.frexp(h)
    hi = float(np.ldexp(np.floor(np.ldexp(m, 26)), int(e) - 26))
    return hi, h - hi


def _power_table() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``10**k = H + L`` to about 106 bits (``H`` the double nearest, ``L`` the double nearest
    the rest) for ``_KMIN <= k <= _KMAX``, with ``H`` split for Dekker's product."""
    h, hh, hl, lo = [], [], [], []
    for k in range(_KMIN, _KMAX + 1):
        exact = Fraction(10) ** k
        big = float(exact)
        top, bottom = _split26(big)
        h.append(big)
        hh.append(top)
        hl.append(bottom)
        lo.append(float(exact - Fraction(big)))
    return (np.array(h), np.array(hh), np.array(hl), np.array(lo))


_H, _HH, _HL, _LO = _power_table()
_SPLIT = 134217729.0  # 2**27 + 1: Veltkamp's split into two 26-bit halves
# the exact powers 10**0 to 10**22, split for Dekker's product
_P_HI, _P_LO = (np.array(t) for t in zip(*(_split26(float(10**k)) for k in range(23)), strict=True))
_EXPONENT = U64(0x7FF0000000000000)
_HALF_ULP = U64(53 << 52)


def _scaled(ax: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(I, f, H)``: ``ax * 10**k = I + f`` with ``I`` an int64 and ``0 <= f < 1`` (to about
    ``2**-106`` relative: Dekker's exact product ``ax * H`` plus ``ax * L``), and ``H``."""
    row = k - _KMIN
    h = _H.take(row)
    hh, hl = _HH.take(row), _HL.take(row)
    p = ax * h
    c = ax * _SPLIT
    ah = c - (c - ax)
    al = ax - ah
    tail = ((ah * hh - p) + ah * hl + al * hh) + al * hl
    tail += ax * _LO.take(row)
    ip = np.floor(p)
    p -= ip
    p += tail
    fl = np.floor(p)
    p -= fl
    return ip.astype(np.int64) + fl.astype(np.int64), p, h


def _decimals(ax: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For positive doubles in ``[_FAST_MIN, _FAST_MAX)``: ``(N, D, e, ok)``: the shortest
    decimal that reads back as ``ax`` (:func:`_short_decimals` where it has at most 15
    significant digits, else :func:`_medium_decimals`, else :func:`_long_decimals`), its
    significand padded to 17 digits
    (``N``, uint64), its count ``D`` of digits without trailing zeros, and the decimal
    exponent ``e`` of its first digit (the number is ``N * 10**(e - 16)``).  ``ok`` is False
    where no decimal was found that reads back as ``ax`` (``N``, ``D``, ``e`` are then
    meaningless: the caller prints those with ``repr``)."""
    e = np.floor(np.log10(ax)).astype(np.int64)
    n17, digits, e, short = _short_decimals(ax, e)
    rest = np.flatnonzero(~short)
    if len(rest):
        n17[rest], digits[rest], short[rest] = _medium_decimals(ax[rest], e[rest])
        long = rest[~short[rest]]
        if len(long):
            n17[long], digits[long], e[long], short[long] = _long_decimals(ax[long], e[long])
    return n17, digits, e, short


def _exact_product(ax: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(p, err)``: ``ax * 10**k = p + err`` exactly (``0 <= k <= 22``: ``10**k`` is a double;
    Dekker's product, ``ax`` split by Veltkamp)."""
    c = ax * _SPLIT
    ah = c - (c - ax)
    al = ax - ah
    hh, hl = _P_HI.take(k), _P_LO.take(k)
    p = ax * (hh + hl)
    err = ((ah * hh - p) + ah * hl + al * hh) + al * hl
    return p, err


def _medium_decimals(ax: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(N, D, ok)`` of :func:`_decimals` for doubles whose shortest decimal has more than 15
    digits, where ``e`` (``floor(log10(ax))`` or one off) is in ``[-6, 14]`` (``ok`` False
    elsewhere, and where ``e`` is off or the 16-digit candidate is not below ``2**53``).

    With ``10**k`` exact, Dekker's product gives ``ax * 10**k`` exactly as ``p + err``, so the
    16- and 17-digit significands nearest ``ax`` (ties to even) follow exactly.  The 16-digit
    one, a double below ``2**53``, reads back as ``ax`` exactly when one division says so (as
    in :func:`_short_decimals`); if it does not, no 16-digit decimal does, and the nearest
    17-digit one is ``repr``'s: a 17-digit decimal within half a unit of its last digit of
    ``ax`` is always within half the spacing of doubles (``5e-17 * ax`` against at least
    ``2**-54 * ax``), so it reads back as ``ax`` without a check."""
    ok = (e >= -6) & (e <= 14)
    k = np.clip(15 - e, 0, 21)
    p, err = _exact_product(ax, k)
    s = np.rint(p)
    d = (p - s) + err  # ax * 10**k - s: exact but next to a half (the rare blurred ties)
    half = s * 0.5
    odd = np.floor(half) != half  # (np.fmod is a libm call per element)
    s += (d > 0.5) | ((d == 0.5) & odd)
    s -= (d < -0.5) | ((d == -0.5) & odd)
    ok &= (s >= 1e15) & (s < 2.0**53)
    sixteen = s / _POW10_FLOAT.take(k) == ax
    p, err = _exact_product(ax, k + 1)  # p an integer: at least 1e16 > 2**53 where ok
    r = np.rint(np.clip(err, -64.0, 64.0))  # (the clip only where not ok: |err| <= 8 else)
    n17 = np.minimum(p, 1e17).astype(np.int64) + r.astype(np.int64)
    ok &= (n17 >= _POW10_INT[16]) & (n17 < _POW10_INT[17])
    n16 = np.minimum(s, 1e16).astype(np.int64) * 10
    n17 += sixteen * (n16 - n17)
    return n17.astype(U64), 17 - sixteen.astype(np.int64), ok


def _short_decimals(
    ax: np.ndarray, e: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_decimals` where the shortest decimal has at most 15 digits (``ok`` False
    elsewhere), ``e`` being ``floor(log10(ax))`` or one off.

    ``s``, the double nearest ``ax * 10**k`` (``k = 14 - e``, ``10**k`` exact for
    ``0 <= k <= 22``) rounded to an integer, is within ``0.18`` of ``ax * 10**k``, so it is
    the only decimal of at most 15 digits that can read back as ``ax`` (those are at least
    ``10**-15 * ax`` apart, more than the spacing of doubles).  Whether it does is then
    settled exactly by one division: ``s`` and ``10**k`` are doubles, so ``s / 10**k``
    rounds the decimal ``s * 10**-k`` correctly, as reading it does (Clinger)."""
    k = 14 - e
    scale = _POW10_FLOAT.take(np.clip(k, 0, 22))
    s = np.rint(ax * scale)
    ok = s / scale == ax
    ok &= s < 1e15  # at most 15 digits: e was not one too small
    ok &= s >= 1e13  # at least 14: e was at most one too big
    ok &= (k >= 0) & (k <= 22)
    at = np.flatnonzero(ok)  # the rest below on these only
    s = s[at]
    fewer = s < 1e14  # e was one too big
    e = e.copy()
    e[at] -= fewer
    count = 15 - fewer
    # trailing zeros in doubles: s / 10**k is an integer exactly when 10**k divides s (the
    # quotient of s < 1e15 is correctly rounded, at least 10**-k off an integer otherwise)
    for p in (8, 4, 2, 1):
        q = s / _POW10_FLOAT[p]
        zeros = np.floor(q) == q
        q -= s
        q *= zeros
        s += q
        count -= p * zeros
    n17 = np.zeros(len(ax), dtype=U64)
    n17[at] = s.astype(U64) * _POW10_INT.take(17 - count).astype(U64)
    digits = np.full(len(ax), 17, dtype=np.int64)
    digits[at] = count
    return n17, digits, e, ok


def _strip_zeros(sig: np.ndarray, digits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``sig`` (int64 of ``digits`` <= 17 digits, the first not 0) without its trailing zeros
    (up to 15), and the count of digits left."""
    for k in (8, 4, 2, 1):  # halving the count each step
        q = sig // _POW10_INT[k]
        zeros = q * _POW10_INT[k] == sig
        q -= sig  # blends, not np.where (see _long_decimals)
        q *= zeros
        sig += q
        digits = digits - k * zeros
    return sig, digits


def _long_decimals(
    ax: np.ndarray, e: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_decimals` from the 15-, 16- and 17-digit significands, ``e`` being
    ``floor(log10(ax))`` or one off.

    The candidate is chosen by its distance to ``ax`` against half the spacing of doubles
    there (a shorter candidate within it reads back as ``ax``, except on the short side of a
    power of two), then checked by parsing it back: a misjudged one is never written."""
    bits = ax.view(U64)
    whole, frac, scale = _scaled(ax, 16 - e)
    for _ in range(2):  # log10 can be one off next to a power of ten
        off = np.flatnonzero((whole >= _POW10_INT[17]) | (whole < _POW10_INT[16]))
        if len(off) == 0:
            break
        e[off] += np.where(whole[off] >= _POW10_INT[17], 1, -1)
        whole[off], frac[off], scale[off] = _scaled(ax[off], 16 - e[off])
    # half the spacing of doubles at ax (2**(E - 53), E its binary exponent; ax is normal), in
    # units of the 17th digit; reading a decimal exactly that far rounds to the even significand
    reach = ((bits & _EXPONENT) - _HALF_ULP).view(np.float64)
    reach *= scale
    even = (bits & U64(1)) == 0
    # np.where costs several times a multiplication (a mispredicted branch per element): the
    # choices below are blends, b + m * (a - b) for a mask m
    sig = whole + ((frac > 0.5) | ((frac == 0.5) & ((whole & 1) == 1)))  # 17 digits, ties even
    digits = np.full(len(ax), 17, dtype=np.int64)
    for p in (16, 15):  # shorter ones where they are near enough
        unit = _POW10_INT[17 - p]
        q = whole // unit
        rest = (whole - q * unit) + frac  # ax's distance above q * unit, in 17th-digit units
        half = float(unit) / 2
        up = (rest > half) | ((rest == half) & ((q & 1) == 1))
        rest = np.abs(rest - up * float(unit))  # to q + 1 where up (exactly unit - rest)
        near = (rest < reach) | ((rest == reach) & even)
        q += up
        q -= sig
        q *= near
        sig += q
        digits -= near * (digits - p)
    carry = sig == _POW10_INT.take(digits)  # rounded up to the next power of ten
    sig[carry] //= 10
    e += carry
    sig, digits = _strip_zeros(sig, digits)
    q = e - digits + 1
    back, undecided = decimal_to_double(sig.astype(U64), q)
    # products too close to a rounding boundary (about one in two hundred): Python decides
    hard = np.flatnonzero(undecided)
    exact = zip(sig[hard].tolist(), q[hard].tolist(), strict=True)
    back[hard] = [float(f"{a}e{b}") for a, b in exact]
    n17 = sig.astype(U64) * _POW10_INT.take(17 - digits).astype(U64)
    return n17, digits, e, back == ax


# --- ASCII digits -----------------------------------------------------------------------------

_ASCII_ZEROS = U64(0x3030303030303030)


def ascii8(v: np.ndarray) -> np.ndarray:
    """The 8 decimal digits of each integer ``0 <= v < 10**8`` (zero-padded) as ASCII in a
    uint64, most significant first in memory (little-endian: the lowest byte).

    Each step splits every lane of the word in two: 4+4 digits in 32-bit lanes, 2+2 in
    16-bit, 1+1 in 8-bit; the divisions by 100 and 10 are multiply-shifts, exact for the lane
    values (below 10**4 and 100)."""
    v = v.astype(U64, copy=False)
    hi = v // U64(10000)
    w = hi | ((v - hi * U64(10000)) << U64(32))
    hi = ((w * U64(5243)) >> U64(19)) & U64(0x0000007F0000007F)
    w = hi | ((w - hi * U64(100)) << U64(16))
    hi = ((w * U64(103)) >> U64(10)) & U64(0x000F000F000F000F)
    w = hi | ((w - hi * U64(10)) << U64(8))
    return w | _ASCII_ZEROS


# The four decimal digits of 0 <= v < 10**4 (zero-padded) as ASCII in the low half of a word
_ASCII4 = np.array([int.from_bytes(b"%04d" % v, "little") for v in range(10**4)], dtype=U64)


def _ascii8_table(v: np.ndarray) -> np.ndarray:
    """:func:`ascii8` by two lookups of four digits (fewer numpy passes than its steps)."""
    high = v // U64(10**4)
    low = v - high * U64(10**4)
    w = _ASCII4.take(low)
    w <<= U64(32)
    w |= _ASCII4.take(high)
    return w


def _digit_words(n17: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 17 digits of each ``n17 < 10**17`` as ASCII bytes 0-16 of three words."""
    lead = n17 // U64(10**16)
    rest = n17 - lead * U64(10**16)
    a = rest // U64(10**8)
    b = _ascii8_table(rest - a * U64(10**8))
    a = _ascii8_table(a)
    return (lead + U64(48)) | (a << U64(8)), (a >> U64(56)) | (b << U64(8)), b >> U64(56)


def _low_bytes(c: int, fill: int) -> int:
    """A word whose lowest ``c`` (0-8) bytes are ``fill`` and the others 0."""
    return int.from_bytes(bytes([fill]) * c + bytes(8 - c), "little")


# For the point at byte p (0-23; 24: none) of three words of digits: by word k, indexed by p,
# the bytes of word k before the point (kept in place), and the point's byte in word k
_KEEP = [
    np.array([_low_bytes(min(max(p - 8 * k, 0), 8), 0xFF) for p in range(25)], dtype=U64)
    for k in range(3)
]
_POINT = [
    np.array([0x2E << (8 * (p - 8 * k)) if 0 <= p - 8 * k < 8 else 0 for p in range(25)], U64)
    for k in range(3)
]
# For text ending at byte z (0-24) of the three words: by word k, indexed by z, its bytes kept
_ZONE = [
    np.array([_low_bytes(min(max(z - 8 * k, 0), 8), 0xFF) for z in range(25)], dtype=U64)
    for k in range(3)
]

# Text before the digits: "-" (sign) then "0." and zeros (exponents -1 to -4), right-aligned in
# the record's first word; key = 5 * sign + (0 for no "0.", else -e)
_LEADS = [
    ("-" if s else "") + ("" if z == 0 else "0." + "0" * (z - 1)) for s in (0, 1) for z in range(5)
]
_LEAD_WORD = np.array(
    [int.from_bytes(t.encode().rjust(8, b"\0"), "little") for t in _LEADS], dtype=U64
)


def _insert_point(w: list[np.ndarray], point: np.ndarray) -> None:
    """Put a decimal point at byte ``point`` (0-23) of the three words ``w`` of digits (in
    place), the bytes from there on one byte later (the last one dropped)."""
    carry = U64(0)
    for k in range(3):
        kept = w[k] & _KEEP[k].take(point)
        moved = w[k] ^ kept
        kept |= moved << U64(8)
        kept |= _POINT[k].take(point)
        kept |= carry
        carry = moved >> U64(56)
        w[k] = kept


def _records(values: np.ndarray, prefix: bytes, lines: np.ndarray) -> np.ndarray:
    """The lines of :func:`float_lines` for the ``(rows, m)`` ``values``, with zero bytes in
    between (the text has none), to be dropped: per line a word of ``prefix`` (right-aligned)
    and per number a 32-byte record of its text (the lead word, then the digits from byte 8,
    or ``repr``'s text from byte 0) and separator (a space, or a line break after a line's
    last), written into ``lines`` (uint64, ``(rows, 1 + 4 m)``) and returned as uint8."""
    rows, m = values.shape
    x = values.reshape(-1)
    ax = np.abs(x)
    fast = (ax >= _FAST_MIN) & (ax < _FAST_MAX)
    if fast.all():
        n17, digits, e, ok = _decimals(ax)
    else:  # the others as 1.0, then zeros as "0.0" and the rest as repr
        other = np.flatnonzero(~fast)
        ax[other] = 1.0
        n17, digits, e, ok = _decimals(ax)
        n17[other] = 0
        digits[other] = 1
        e[other] = 0
        ok[other] = x[other] == 0
    slow = np.flatnonzero(~ok)
    w = list(_digit_words(n17))

    # blends, not np.where (see _long_decimals)
    positional = (e >= -4) & (e < 16)
    below_one = e < 0
    # the point's place in the digits (24: none): positional after the units digit (none below
    # one: the lead word has "0."), else after the first digit unless it is the only one
    point = 1 + 23 * (digits == 1)
    point += positional * (e + 1 + below_one * (23 - e) - point)
    # the end of the digits with the point: a positional number has its digits, zeros up to
    # the units (e >= 0) and a point, or a zero after it ("1.0"); the others their digits and
    # a point after the first if there are more
    zone = digits + (digits > 1)
    zone += positional * (np.maximum(digits, e + 2) + 1 - below_one - zone)
    lead_key = (positional & below_one) * -e
    lead_key += 5 * np.signbit(x)
    lines[:, 0] = int.from_bytes(prefix.rjust(8, b"\0"), "little")
    rec = lines[:, 1:].reshape(rows, m, 4)
    rec[:, :, 0] = _LEAD_WORD.take(lead_key).reshape(rows, m)
    # the point, on the numbers that have one in their digits (not those below one)
    dotted = np.flatnonzero(point < 24)
    if len(dotted) == len(point):
        _insert_point(w, point)
    elif len(dotted):
        part = [word[dotted] for word in w]
        _insert_point(part, point[dotted])
        for word, done in zip(w, part, strict=True):
            word[dotted] = done
    zone = zone.reshape(rows, m)
    for k in range(3):  # straight into the lines
        np.bitwise_and(w[k].reshape(rows, m), _ZONE[k].take(zone), out=rec[:, :, k + 1])
    # the exponent ("e-05", "e+100") at the record's bytes 26-30 and the separator at byte 31,
    # whatever the digits' length: the zero bytes in between are dropped
    rec[:, :-1, 3] |= U64(ord(" ") << 56)
    rec[:, -1, 3] |= U64(ord("\n") << 56)
    sci = np.flatnonzero(~positional)
    if len(sci):
        ex = e[sci]
        mag = np.abs(ex)
        big = mag >= 100
        text = (
            ord("e")
            | np.where(ex < 0, ord("-"), ord("+")) << 8
            | big * (mag // 100 + 48) << 16
            | ((mag // 10) % 10 + 48) << 24
            | (mag % 10 + 48) << 32
        ).astype(U64)
        text <<= U64(16)  # to bytes 2-6 of the word (a zero byte for a 2-digit exponent)
        rec[sci // m, sci % m, 3] |= text

    if len(slow):  # nan, infinities, subnormals, huge and the few misjudged: Python's repr
        texts = np.array([repr(v).encode() for v in x[slow].tolist()], dtype="S24")
        row, col = slow // m, slow % m
        rec[row, col, :3] = texts.view(U64).reshape(-1, 3)
        rec[row, col, 3] &= U64(0xFF << 56)  # the separator
    return lines.view(np.uint8).reshape(-1)


def float_lines(values: np.ndarray, prefix: bytes) -> bytes:
    """One line per row of the ``(n, m)`` float64 ``values``: ``prefix`` then the row's numbers
    separated by single spaces, each the shortest decimal that reads back as the same double
    (as Python's ``repr`` writes it: ``nan``, ``inf``, ``-0.0``, ``1e-05``, ``0.1``), then a
    line break.

    Returns:
        the text as ASCII bytes.
    """
    return b"".join(float_pieces(values, prefix))


def float_pieces(values: np.ndarray, prefix: bytes) -> list[bytes | memoryview]:
    """:func:`float_lines` in consecutive pieces (a few thousand lines each), to be written one
    after another without joining them."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise ValueError("float_lines takes an (n, m) array")
    n, m = values.shape
    if n == 0:
        return []
    if len(prefix) > 8 or 0 in prefix:
        raise ValueError("float_lines takes a prefix of at most 8 bytes, none zero")
    pieces: list[bytes | memoryview] = []
    # one buffer for every chunk: a fresh one costs a page fault every 4 kB
    buffer = np.empty((min(n, _CHUNK_ROWS), 1 + 4 * m), dtype=U64)
    for lo in range(0, n, _CHUNK_ROWS):
        chunk = values[lo : lo + _CHUNK_ROWS]
        text = _records(chunk, prefix, buffer[: len(chunk)])
        pieces.append(without_zero_bytes(text))
    return pieces


def without_zero_bytes(text: np.ndarray) -> bytes:
    """The ``uint8`` ``text`` without its zero bytes (the gaps of fixed-place records).

    ``bytes.translate`` deletes them in one C loop: faster than numpy's boolean mask, which
    makes a mask, counts it and then compacts."""
    return text.tobytes().translate(None, b"\0")
