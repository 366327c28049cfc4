"""Doubles as the shortest decimal text that reads back exactly, in bulk.

The text writers print millions of coordinates; Python's ``repr`` of each (the shortest
round-trip decimal) costs about a microsecond a number.  This module gives the same text with
numpy operations on whole arrays:

* candidates: ``|x|`` scaled by ``10**k`` (a double-double power of ten and Dekker's exact
  product: about 106 correct bits) gives the integer part and fraction of
  ``|x| * 10**(16 - e)``, ``e`` the decimal exponent; from them the 17-, 16- and 15-digit
  significands rounded to nearest (ties to even), and the shortest one whose distance to
  ``|x|`` is within half the spacing of doubles there is chosen;
* verification: every chosen decimal is parsed back with the readers' exact decimal-to-double
  conversion (:func:`.numparse.decimal_to_double`; Python's ``float`` for the few it leaves
  undecided) and must give ``x`` again, else Python's ``repr`` prints that number, as it does
  ``nan``, infinities, subnormals and magnitudes beyond ``1e290``.  The exact round trip is
  thus guaranteed by the check itself, not by the arithmetic before it;
* text: the digits eight at a time as ASCII (integer "SWAR" steps), the decimal point put in
  with byte masks and shifts, laid out as ``repr`` does (positional for exponents
  ``-4 <= e < 16``, else ``d.ddde+XX``) in fixed 40-byte records, which a byte mask then
  packs into the file's text.

The text is ``repr``'s (the shortest round-trip decimal, the nearest among those) except in
rare cases, where a longer decimal, still exact, is written: a shorter one exactly half a
spacing of doubles away from ``|x| >= 1e17`` (where the inexact ``10**k``, ``k < 0``, blurs
the tie) or on the short side of a power of two (whose rounding interval is lopsided).
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from .numparse import decimal_to_double

__all__ = ["ascii8", "float_lines", "float_pieces"]

U64 = np.uint64
_CHUNK_ROWS = 1 << 15  # lines per chunk: temporaries of a few megabytes, not of the whole mesh
_W = 40  # bytes per number record: 8 of prefix ("-0.000"), 24 of digits, exponent, separator
_FAST_MIN, _FAST_MAX = 1e-290, 1e290  # |x| the vectorised path handles
_KMIN, _KMAX = -290, 308  # powers of ten it scales by
_POW10_INT = np.array([10**k for k in range(19)], dtype=np.int64)


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
    """For positive doubles in ``[_FAST_MIN, _FAST_MAX)``: ``(N, D, e, ok)``: the shortest of
    the 15-, 16- and 17-digit significands that reads back as ``ax``, padded to 17 digits
    (``N``, uint64), its count ``D`` of digits without trailing zeros, and the decimal
    exponent ``e`` of its first digit (the number is ``N * 10**(e - 16)``).  ``ok`` is False
    where the chosen significand does not read back as ``ax`` (``N``, ``D``, ``e`` are then
    meaningless: the caller prints those with ``repr``).

    The candidate is chosen by its distance to ``ax`` against half the spacing of doubles
    there (a shorter candidate within it reads back as ``ax``, except on the short side of a
    power of two), then checked by parsing it back: a misjudged one is never written."""
    bits = ax.view(U64)
    e = np.floor(np.log10(ax)).astype(np.int64)
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
    sig = whole + ((frac > 0.5) | ((frac == 0.5) & (whole & 1 == 1)))  # 17 digits, ties to even
    digits = np.full(len(ax), 17, dtype=np.int64)
    for p in (16, 15):  # shorter ones where they are near enough
        unit = _POW10_INT[17 - p]
        q = whole // unit
        rest = (whole - q * unit) + frac  # ax's distance above q * unit, in 17th-digit units
        half = float(unit) / 2
        up = (rest > half) | ((rest == half) & (q & 1 == 1))
        rest = np.where(up, unit - rest, rest)
        near = (rest < reach) | ((rest == reach) & even)
        sig = np.where(near, q + up, sig)
        digits = np.where(near, p, digits)
    carry = sig == _POW10_INT.take(digits)  # rounded up to the next power of ten
    sig[carry] //= 10
    e += carry
    for k in (8, 4, 2, 1):  # trailing zeros, halving the count each step
        q = sig // _POW10_INT[k]
        zeros = q * _POW10_INT[k] == sig
        sig = np.where(zeros, q, sig)
        digits -= k * zeros
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


def _digit_words(n17: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 17 digits of each ``n17 < 10**17`` as ASCII bytes 0-16 of three words."""
    lead = n17 // U64(10**16)
    rest = n17 - lead * U64(10**16)
    a = rest // U64(10**8)
    b = ascii8(rest - a * U64(10**8))
    a = ascii8(a)
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

# Record bytes kept: a range [a, b) of the 40, a <= 8, as a row of this table (index a * 41 + b)
_MASKS = np.array([[a <= i < b for i in range(_W)] for a in range(9) for b in range(_W + 1)])

# Text before the digits: "-" (sign) then "0." and zeros (exponents -1 to -4), right-aligned in
# the record's first word; key = 5 * sign + (0 for no "0.", else -e)
_LEADS = [
    ("-" if s else "") + ("" if z == 0 else "0." + "0" * (z - 1)) for s in (0, 1) for z in range(5)
]
_LEAD_WORD = np.array(
    [int.from_bytes(t.encode().rjust(8, b"\0"), "little") for t in _LEADS], dtype=U64
)
_LEAD_LEN = np.array([len(t) for t in _LEADS], dtype=np.int64)


def _records(x: np.ndarray, width: int, sep_last: bytes) -> tuple[np.ndarray, np.ndarray]:
    """``(records, keep)``: each number of the row-major ``x`` (``width`` per line) as its text
    and separator (a space, or ``sep_last`` after a line's last) in a 40-byte record, all in
    one uint8 array, and the bytes of it to keep."""
    n = len(x)
    ax = np.abs(x)
    fast = (ax >= _FAST_MIN) & (ax < _FAST_MAX)
    if fast.all():
        n17, digits, e, ok = _decimals(ax)
    else:  # the others as 1.0, then zeros as "0.0" and the rest as repr
        n17, digits, e, ok = _decimals(np.where(fast, ax, 1.0))
        n17 = np.where(fast, n17, U64(0))
        digits = np.where(fast, digits, 1)
        e = np.where(fast, e, 0)
        ok &= fast | (ax == 0)
    slow = np.flatnonzero(~ok)
    w = _digit_words(n17)

    positional = (e >= -4) & (e < 16)
    below_one = e < 0
    # the point's place in the digits (24: none), and the digits' bytes with it
    point = np.where(positional, np.where(below_one, 24, e + 1), np.where(digits == 1, 24, 1))
    zone = np.where(below_one, digits, np.maximum(digits, e + 2) + 1)
    zone = np.where(positional, zone, digits + (digits > 1))
    lead_key = np.where(positional & below_one, -e, 0)
    lead_key += 5 * np.signbit(x)
    rec = np.empty((n, _W // 8), dtype=U64)  # every byte kept is written below
    rec[:, 0] = _LEAD_WORD.take(lead_key)
    carry = U64(0)
    for k in range(3):
        kept = w[k] & _KEEP[k].take(point)
        moved = w[k] ^ kept
        kept |= moved << U64(8)
        kept |= _POINT[k].take(point)
        kept |= carry
        rec[:, k + 1] = kept
        carry = moved >> U64(56)
    start = 8 - _LEAD_LEN.take(lead_key)
    end = zone + 8
    flat = rec.view(np.uint8).reshape(-1)
    row_at = np.arange(0, n * _W, _W, dtype=np.int64)

    sci = np.flatnonzero(~positional)
    if len(sci):
        ex = e[sci]
        mag = np.abs(ex)
        big = mag >= 100
        base = row_at[sci] + end[sci]
        flat[base] = ord("e")
        flat[base + 1] = np.where(ex < 0, ord("-"), ord("+"))
        flat[base + 2] = np.where(big, mag // 100, (mag // 10) % 10) + 48
        flat[base + 3] = np.where(big, (mag // 10) % 10, mag % 10) + 48
        flat[base + 4] = mag % 10 + 48  # overwritten by the separator below unless big
        end[sci] += 4 + big

    if len(slow):  # nan, infinities, subnormals, huge and the few misjudged: Python's repr
        texts = np.array([repr(v).encode() for v in x[slow].tolist()], dtype="S24")
        rec[slow, 1:4] = texts.view(U64).reshape(-1, 3)
        start[slow] = 8
        end[slow] = np.char.str_len(texts) + 8

    sep_at = row_at + end
    flat[sep_at] = ord(" ")
    last = sep_at[width - 1 :: width]
    for i, byte in enumerate(sep_last):
        flat[last + i] = byte
    end[width - 1 :: width] += len(sep_last) - 1
    end += 1
    return rec.view(np.uint8).reshape(-1), _MASKS.take(start * (_W + 1) + end, axis=0).reshape(-1)


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
    sep_last = b"\n" + prefix
    pieces: list[bytes | memoryview] = [prefix]
    for lo in range(0, n, _CHUNK_ROWS):
        rec, keep = _records(values[lo : lo + _CHUNK_ROWS].reshape(-1), m, sep_last)
        packed = rec[keep]
        if lo + _CHUNK_ROWS >= n:  # no line after the last
            packed = packed[: len(packed) - len(prefix)]
        pieces.append(memoryview(packed))
    return pieces
