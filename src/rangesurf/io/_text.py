"""Fast parsing of whitespace-separated ASCII numbers (the bodies of ``.3d`` and ASCII PLY files).

`parse_numbers` reads every token of a text in one compiled pass over its
bytes and returns the numbers with the count of tokens on each line, so a
reader checks its column layout with array operations and names the exact
line of a bad token.

Tokens follow the grammar of C's ``strtod`` and `numpy.loadtxt`::

    [+-] (digits [. [digits]] | . digits) [(e|E) [+-] digits]
    [+-] (nan | inf | infinity)          (any letter case)

Tokens are separated by ASCII whitespace (space, ``\\t``, ``\\n``, ``\\v``,
``\\f``, ``\\r``) and lines end at ``\\n`` (so ``\\r\\n`` works). Every
number is the correctly rounded double, the same as ``float(token)``:

* up to 19 significant digits are gathered into an integer mantissa ``w``
  and a decimal exponent ``q``;
* ``w <= 2**53`` and ``|q| <= 22`` (most data) is one exact multiplication
  or division by a power of ten (Clinger's fast path);
* otherwise the Eisel-Lemire algorithm scales ``w`` by a 128-bit power of
  five from a table, which is exact for all 19-digit mantissas;
* a token with more than 19 significant digits is tried with ``w`` and
  ``w + 1``; in the rare case that they round differently the token is
  handed to Python's ``float``.

Python's ``float`` also takes ``1_000``; like `numpy.loadtxt`, this does not.

References
----------
W. D. Clinger, "How to read floating point numbers accurately", PLDI 1990.
D. Lemire, "Number parsing at a gigabyte per second", Software: Practice
and Experience 51(8), 2021; N. Mushtak and D. Lemire, "Fast number parsing
without fallback", Software: Practice and Experience 53(6), 2023.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numba
import numpy as np

__all__ = ["BadToken", "NumberSyntaxError", "ParsedNumbers", "parse_numbers", "split_lists"]

# --------------------------------------------------------------------------
# Tables and constants of the kernel (numba freezes module-level arrays and
# NumPy scalars into the compiled code as constants).
# --------------------------------------------------------------------------

# Exact powers of ten for Clinger's fast path (10**22 is the largest exact double).
_POW10 = np.array([10.0**k for k in range(23)])
_MAX_EXACT_MANTISSA = np.uint64(2**53)
_MAX_DIGITS = 19  # significant digits that fit a uint64 mantissa
_EXPONENT_CAP = 100_000  # beyond any double's exponent; stops the int overflowing

# Eisel-Lemire for binary64.
_SMALLEST_POWER_OF_TEN = -342
_LARGEST_POWER_OF_TEN = 308
_MIN_EXPONENT_ROUND_TO_EVEN = -4
_MAX_EXPONENT_ROUND_TO_EVEN = 23
_MINIMUM_EXPONENT = -1023
_INFINITE_POWER = 0x7FF
_MANTISSA_BITS = 52


def _powers_of_five_128() -> tuple[np.ndarray, np.ndarray]:
    """High and low 64 bits of ``5**q`` for q in -342..308, normalised to 128 bits.

    The table of Lemire's ``fast_float``: positive powers truncated, negative
    ones ``2**b // 5**-q + 1`` (rounded up) then truncated, which the
    algorithm's proofs of correctness rely on.
    """
    high, low = [], []
    for q in range(_SMALLEST_POWER_OF_TEN, _LARGEST_POWER_OF_TEN + 1):
        if q < 0:
            power = 5**-q
            z = power.bit_length()  # smallest z with 2**z >= 5**-q (5**-q is never a power of two)
            b = z + 127 if q >= -17 else 2 * z + 64
            number = (1 << b) // power + 1
        else:
            number = 5**q
        length = number.bit_length()
        number = number << (128 - length) if length < 128 else number >> (length - 128)
        high.append(number >> 64)
        low.append(number & (2**64 - 1))
    return np.array(high, dtype=np.uint64), np.array(low, dtype=np.uint64)


_POW5_HIGH, _POW5_LOW = _powers_of_five_128()

_U0, _U1, _U3 = np.uint64(0), np.uint64(1), np.uint64(3)
_U10 = np.uint64(10)
_MASK32 = np.uint64(0xFFFFFFFF)
_PRECISION_MASK = np.uint64(0xFFFFFFFFFFFFFFFF >> (_MANTISSA_BITS + 3))
_HIDDEN_BIT = np.uint64(1 << _MANTISSA_BITS)
_OVERFLOW_BIT = np.uint64(2 << _MANTISSA_BITS)

# What the kernel reports about a token.
_OK, _NEEDS_PYTHON, _BAD = 0, 1, 2


# --------------------------------------------------------------------------
# Kernel.
# --------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _multiply_64(a, b):  # pragma: no cover - compiled
    """``a * b`` of two uint64 as (high, low) uint64 words."""
    a_low, a_high = a & _MASK32, a >> np.uint64(32)
    b_low, b_high = b & _MASK32, b >> np.uint64(32)
    low_low = a_low * b_low
    low_high = a_low * b_high
    high_low = a_high * b_low
    middle = (low_low >> np.uint64(32)) + (low_high & _MASK32) + (high_low & _MASK32)
    low = (low_low & _MASK32) | (middle << np.uint64(32))
    high = a_high * b_high + (low_high >> np.uint64(32)) + (high_low >> np.uint64(32)) + (middle >> np.uint64(32))
    return high, low


@numba.njit(cache=True, nogil=True)
def _leading_zeros(w):  # pragma: no cover - compiled
    """Leading zero bits of a uint64 (numba has no portable intrinsic for it)."""
    count = 0
    for bits in (32, 16, 8, 4, 2, 1):
        if (w >> np.uint64(64 - bits)) == _U0:
            w = w << np.uint64(bits)
            count += bits
    return count


@numba.njit(cache=True, nogil=True)
def _eisel_lemire(w, q):  # pragma: no cover - compiled
    """The double nearest ``w * 10**q`` for a uint64 ``w > 0`` (ties to even)."""
    if q < _SMALLEST_POWER_OF_TEN:
        return 0.0
    if q > _LARGEST_POWER_OF_TEN:
        return np.inf
    lz = _leading_zeros(w)
    w = w << np.uint64(lz)
    index = q - _SMALLEST_POWER_OF_TEN
    high, low = _multiply_64(w, _POW5_HIGH[index])
    if (high & _PRECISION_MASK) == _PRECISION_MASK:
        # The low bits might carry into the kept ones: add the next 64 bits.
        second_high, _ = _multiply_64(w, _POW5_LOW[index])
        low = low + second_high
        if second_high > low:
            high = high + _U1
    upper_bit = np.int64(high >> np.uint64(63))
    shift = np.uint64(upper_bit + 64 - _MANTISSA_BITS - 3)
    mantissa = high >> shift
    # floor(q * log2(10)) + 63 in fixed point (exact for |q| < 350), then the shifts.
    power2 = (((152170 + 65536) * q) >> 16) + 63 + upper_bit - lz - _MINIMUM_EXPONENT
    if power2 <= 0:  # subnormal
        if -power2 + 1 >= 64:
            return 0.0
        mantissa = mantissa >> np.uint64(-power2 + 1)
        mantissa = (mantissa + (mantissa & _U1)) >> _U1
        return math.ldexp(float(mantissa), -1074)
    if (low <= _U1 and q >= _MIN_EXPONENT_ROUND_TO_EVEN and q <= _MAX_EXPONENT_ROUND_TO_EVEN
            and (mantissa & _U3) == _U1 and (mantissa << shift) == high):
        # Exactly halfway between two doubles: round down to the even one.
        mantissa = mantissa & ~_U1
    mantissa = (mantissa + (mantissa & _U1)) >> _U1
    if mantissa >= _OVERFLOW_BIT:
        mantissa = _HIDDEN_BIT
        power2 += 1
    if power2 >= _INFINITE_POWER:
        return np.inf
    return math.ldexp(float(mantissa), power2 - 1075)


@numba.njit(cache=True, nogil=True, inline="always")
def _byte(buffer, i):  # pragma: no cover - compiled
    # An unsigned index spares numba's negative-index check on every byte
    # (the hot loops run about a quarter faster).
    return buffer[np.uint64(i)]


@numba.njit(cache=True, nogil=True, inline="always")
def _is_space(c):  # pragma: no cover - compiled
    return c == 32 or (c >= 9 and c <= 13)


@numba.njit(cache=True, nogil=True, inline="always")
def _is_digit(c):  # pragma: no cover - compiled
    return c >= 48 and c <= 57


@numba.njit(cache=True, nogil=True)
def _matches_word(buffer, i, n, word):  # pragma: no cover - compiled
    """Whether ``buffer[i:]`` starts with the lower-case ASCII ``word``, in any case."""
    if i + len(word) > n:
        return False
    for k in range(len(word)):
        if (buffer[i + k] | 32) != word[k]:  # | 32 lower-cases ASCII letters
            return False
    return True


_NAN_WORD = np.frombuffer(b"nan", dtype=np.uint8).copy()
_INF_WORD = np.frombuffer(b"inf", dtype=np.uint8).copy()
_INFINITY_WORD = np.frombuffer(b"infinity", dtype=np.uint8).copy()


@numba.njit(cache=True, nogil=True)
def _long_significand(buffer, i, end):  # pragma: no cover - compiled
    """``(w, q, truncated)`` of the digits (and point) in ``buffer[i:end]``, keeping 19 significant digits.

    The slow path of `_parse_token`, for more than 19 digit characters:
    leading zeros do not count, later digits are dropped (``truncated``
    says whether any of them was not zero).
    """
    w = _U0
    digits = 0
    q = 0
    truncated = False
    after_point = False
    while i < end:
        c = _byte(buffer, i)
        i += 1
        if c == 46:  # .
            after_point = True
            continue
        if digits < _MAX_DIGITS:
            w = w * _U10 + np.uint64(c - 48)
            if w != _U0:
                digits += 1
            if after_point:
                q -= 1
        else:
            if not after_point:
                q += 1
            truncated |= c != 48
    return w, q, truncated


@numba.njit(cache=True, nogil=True, inline="always")
def _parse_token(buffer, i, n):  # pragma: no cover - compiled
    """Parse the token at ``buffer[i]``: ``(value, end, status)``."""
    start = i
    negative = False
    c = _byte(buffer, i)
    if c == 45 or c == 43:  # - +
        negative = c == 45
        i += 1
    after_sign = i
    # Every digit goes into w; more than 19 (rare) are redone by _long_significand.
    w = _U0
    while i < n and _is_digit(_byte(buffer, i)):
        w = w * _U10 + np.uint64(_byte(buffer, i) - 48)
        i += 1
    digit_characters = i - after_sign
    q = 0
    if i < n and _byte(buffer, i) == 46:  # .
        i += 1
        fraction_start = i
        while i < n and _is_digit(_byte(buffer, i)):
            w = w * _U10 + np.uint64(_byte(buffer, i) - 48)
            i += 1
        q = fraction_start - i
        digit_characters -= q
    if digit_characters == 0:
        i = after_sign  # "nan" / "inf" follow the sign directly ("-.nan" is bad)
        value = np.nan
        if _matches_word(buffer, i, n, _INFINITY_WORD):
            value, i = np.inf, i + 8
        elif _matches_word(buffer, i, n, _INF_WORD):
            value, i = np.inf, i + 3
        elif _matches_word(buffer, i, n, _NAN_WORD):
            i += 3
        else:
            return np.nan, start, _BAD
        if i < n and not _is_space(_byte(buffer, i)):
            return np.nan, start, _BAD
        return -value if negative else value, i, _OK
    truncated = False
    if digit_characters > _MAX_DIGITS:
        w, q, truncated = _long_significand(buffer, after_sign, i)
    if i < n and (_byte(buffer, i) == 101 or _byte(buffer, i) == 69):  # e E
        i += 1
        exponent_negative = False
        if i < n and (_byte(buffer, i) == 45 or _byte(buffer, i) == 43):
            exponent_negative = _byte(buffer, i) == 45
            i += 1
        if i >= n or not _is_digit(_byte(buffer, i)):
            return np.nan, start, _BAD
        exponent = 0
        while i < n and _is_digit(_byte(buffer, i)):
            if exponent < _EXPONENT_CAP:
                exponent = exponent * 10 + (_byte(buffer, i) - 48)
            i += 1
        q += -exponent if exponent_negative else exponent
    if i < n and not _is_space(_byte(buffer, i)):
        return np.nan, start, _BAD

    status = _OK
    if w == _U0:
        value = 0.0
    elif not truncated and w <= _MAX_EXACT_MANTISSA and -22 <= q <= 22:
        # Clinger: both operands are exact, so one rounding gives the nearest double.
        value = float(w) * _POW10[q] if q >= 0 else float(w) / _POW10[-q]
    else:
        value = _eisel_lemire(w, q)
        if truncated and _eisel_lemire(w + _U1, q) != value:
            status = _NEEDS_PYTHON  # the dropped digits decide the rounding
    return -value if negative else value, i, status


@numba.njit(cache=True, nogil=True)
def _count_newlines(buffer, start):  # pragma: no cover - compiled
    """Lines of ``buffer[start:]`` less one: the size of `parse_numbers`' line counts."""
    count = 0
    for i in range(start, buffer.size):
        count += _byte(buffer, i) == 10  # branch-free, so LLVM vectorises it
    return count


@numba.njit(cache=True, nogil=True)
def _parse_numbers_kernel(buffer, start, values, tokens_per_line, needs_python):  # pragma: no cover - compiled
    """Parse every token of ``buffer[start:]`` into ``values``.

    Returns ``(tokens, lines, n_needs_python, bad_token, bad_offset)``:
    ``tokens_per_line[:lines]`` is filled (all of it when sized by
    `_count_newlines`); ``needs_python[:n_needs_python]`` holds (index,
    byte offset) of the tokens to convert in Python; ``bad_token`` is the
    index of the first token that is not a number, -1 if none. A bad token
    is stored as NaN and parsing goes on, so the line counts are complete.
    """
    n = buffer.size
    i = start
    token = 0
    line = 0
    on_line = 0
    n_needs_python = 0
    bad_token = -1
    bad_offset = -1
    while i < n:
        c = _byte(buffer, i)
        if c == 10:
            tokens_per_line[line] = on_line
            line += 1
            on_line = 0
            i += 1
        elif _is_space(c):
            i += 1
        else:
            value, end, status = _parse_token(buffer, i, n)
            if status == _BAD:
                if bad_token < 0:
                    bad_token, bad_offset = token, i
                end = i + 1
                while end < n and not _is_space(_byte(buffer, end)):
                    end += 1
            elif status == _NEEDS_PYTHON:
                needs_python[n_needs_python, 0] = token
                needs_python[n_needs_python, 1] = i
                n_needs_python += 1
            values[token] = value
            token += 1
            on_line += 1
            i = end
    tokens_per_line[line] = on_line
    return token, line + 1, n_needs_python, bad_token, bad_offset


@numba.njit(cache=True, nogil=True)
def _split_lists_kernel(values, tokens_per_line, lengths, items):  # pragma: no cover - compiled
    """Split lines of ``length item...`` into ``lengths`` and ``items``.

    Returns ``(n_items, first_empty_line, first_wrong_line)``, -1 where there
    is none; a line's length counts as 0 when it is empty or wrong.
    """
    n_items = 0
    token = 0
    first_empty = -1
    first_wrong = -1
    for line in range(tokens_per_line.size):
        count = tokens_per_line[line]
        length = 0
        if count == 0:
            if first_empty < 0:
                first_empty = line
        elif values[token] != count - 1:  # also for a NaN length
            if first_wrong < 0:
                first_wrong = line
        else:
            length = count - 1
            for k in range(token + 1, token + count):
                items[n_items] = values[k]
                n_items += 1
        lengths[line] = length
        token += count
    return n_items, first_empty, first_wrong


# --------------------------------------------------------------------------
# Public wrapper.
# --------------------------------------------------------------------------

_TOKEN = re.compile(rb"[^ \t\n\v\f\r]+")


@dataclass(frozen=True)
class BadToken:
    """A token that is not a number.

    Attributes
    ----------
    index : int
        Its position among all tokens (its slot in ``values`` holds NaN).
    line : int
        Its line, counting from 0 at the ``start`` offset given to `parse_numbers`.
    offset : int
        Byte offset of its first character in the data.
    text : bytes
        The token.
    """

    index: int
    line: int
    offset: int
    text: bytes


class NumberSyntaxError(ValueError):
    """A token of the text is not a number; ``bad`` says which and where."""

    def __init__(self, bad: BadToken) -> None:
        self.bad = bad
        super().__init__(f"line {bad.line + 1}: expected a number, got {bad.text[:40]!r}")


@dataclass(frozen=True)
class ParsedNumbers:
    """Every number of a text in order, and how many tokens each line holds.

    Attributes
    ----------
    values : (T,) float64
        The numbers, line after line (NaN at a bad token).
    tokens_per_line : (L,) int64
        Tokens on each line; ``L`` is the number of ``\\n`` plus one (the
        text after the last ``\\n``, empty for a text ending in one).
        Blank lines count 0.
    bad : BadToken or None
        The first token that is not a number (only with ``strict=False``).
    """

    values: np.ndarray
    tokens_per_line: np.ndarray
    bad: BadToken | None = None


def parse_numbers(data: bytes, *, start: int = 0, strict: bool = True) -> ParsedNumbers:
    """Parse the whitespace-separated numbers of ``data[start:]``.

    Parameters
    ----------
    data : bytes
        ASCII text (other bytes are only allowed inside bad tokens).
    start : int
        Byte offset to begin at (after a header); lines count from there.
    strict : bool
        Raise at the first token that is not a number. With False, it is
        reported in ``bad`` instead and parsed as NaN, so that a caller can
        check its line layout first or ignore data it does not read.

    Returns
    -------
    ParsedNumbers

    Raises
    ------
    NumberSyntaxError
        With ``strict``, for the first token that is not a number.

    Examples
    --------
    >>> parsed = parse_numbers(b"1 2.5 -3e2\\n\\n+inf 4\\n")
    >>> parsed.values.tolist(), parsed.tokens_per_line.tolist()
    ([1.0, 2.5, -300.0, inf, 4.0], [3, 0, 2, 0])
    """
    if not 0 <= start <= len(data):
        raise ValueError(f"start {start} is outside the data (0..{len(data)})")
    buffer = np.frombuffer(data, dtype=np.uint8)
    size = len(data) - start
    tokens_per_line = np.empty(_count_newlines(buffer, start) + 1, dtype=np.int64)
    # Tokens are at least one byte plus a separator; the unused end of the
    # buffer is never written (so never paged in) and is cut off below.
    values = np.empty((size + 1) // 2, dtype=np.float64)
    # A token needing Python has 20 or more digits, and a separator.
    needs_python = np.empty(((size + 1) // 21 + 1, 2), dtype=np.int64)
    tokens, _, n_needs_python, bad_token, bad_offset = _parse_numbers_kernel(
        buffer, start, values, tokens_per_line, needs_python,
    )
    values.resize(tokens, refcheck=False)  # shrinks in place; nothing else refers to it yet
    for token, offset in needs_python[:n_needs_python].tolist():
        values[token] = float(_TOKEN.match(data, offset).group())
    bad = None
    if bad_token >= 0:
        bad = BadToken(bad_token, data.count(b"\n", start, bad_offset), bad_offset,
                       _TOKEN.match(data, bad_offset).group())
        if strict:
            raise NumberSyntaxError(bad)
    return ParsedNumbers(values, tokens_per_line, bad)


def split_lists(values: np.ndarray, tokens_per_line: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Split lines that each hold a list, its length first: ``3 7 8 9``.

    Parameters
    ----------
    values : (T,) float64
        The numbers of the lines, as `parse_numbers` gives them.
    tokens_per_line : (L,) int64
        How many of ``values`` each line holds (``T`` in all).

    Returns
    -------
    lengths : (L,) int64
        Items on each line (0 for an empty line or a wrong length).
    items : float64
        The items of all lines, in order.
    first_empty, first_wrong : int
        The first line without any number, and the first whose length is not
        the number of items after it (not a whole number, or NaN); -1 if none.

    Examples
    --------
    >>> lengths, items, empty, wrong = split_lists(np.array([0.0, 2, 5, 6, 1, 7]), np.array([1, 3, 2]))
    >>> lengths.tolist(), items.tolist(), empty, wrong
    ([0, 2, 1], [5.0, 6.0, 7.0], -1, -1)
    """
    values = np.ascontiguousarray(values, dtype=np.float64)
    tokens_per_line = np.ascontiguousarray(tokens_per_line, dtype=np.int64)
    if tokens_per_line.sum() != len(values):
        raise ValueError(f"tokens_per_line adds up to {tokens_per_line.sum()}, there are {len(values)} values")
    lengths = np.empty(len(tokens_per_line), dtype=np.int64)
    items = np.empty(len(values), dtype=np.float64)  # at most all values (empty lines hold no length)
    n_items, first_empty, first_wrong = _split_lists_kernel(values, tokens_per_line, lengths, items)
    items.resize(n_items, refcheck=False)  # shrinks in place; nothing else refers to it yet
    return lengths, items, first_empty, first_wrong


# --------------------------------------------------------------------------
# Plain reference (what the tests compare the kernel against).
# --------------------------------------------------------------------------

_NUMBER = re.compile(
    rb"[+-]?(?:(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|[nN][aA][nN]|[iI][nN][fF](?:[iI][nN][iI][tT][yY])?)"
)


def _parse_numbers_reference(data: bytes, *, start: int = 0) -> ParsedNumbers:
    """`parse_numbers` with ``strict=False`` in plain Python: `re` for the grammar, `float` for the value."""
    values: list[float] = []
    counts: list[int] = []
    bad = None
    offset = start
    for line_index, line in enumerate(data[start:].split(b"\n")):
        counts.append(0)
        for match in _TOKEN.finditer(line):
            token = match.group()
            if _NUMBER.fullmatch(token):
                values.append(float(token))
            else:
                if bad is None:
                    bad = BadToken(len(values), line_index, offset + match.start(), token)
                values.append(math.nan)
            counts[-1] += 1
        offset += len(line) + 1
    return ParsedNumbers(np.array(values, dtype=np.float64), np.array(counts, dtype=np.int64), bad)


def _split_lists_reference(values: np.ndarray, tokens_per_line: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """`split_lists` line by line in plain Python."""
    lengths: list[int] = []
    items: list[float] = []
    first_empty = first_wrong = -1
    token = 0
    values = np.asarray(values, dtype=np.float64).tolist()
    for line, count in enumerate(np.asarray(tokens_per_line).tolist()):
        row = values[token:token + count]
        token += count
        if not row:
            first_empty = line if first_empty < 0 else first_empty
            lengths.append(0)
        elif row[0] != count - 1:
            first_wrong = line if first_wrong < 0 else first_wrong
            lengths.append(0)
        else:
            lengths.append(count - 1)
            items.extend(row[1:])
    return np.array(lengths, dtype=np.int64), np.array(items, dtype=np.float64), first_empty, first_wrong
