"""ASCII number parsing kernel: against its plain reference and Python's float()."""

from __future__ import annotations

import math
import zlib
from decimal import Decimal, localcontext

import numpy as np
import pytest

from rangesurf.io._text import (
    NumberSyntaxError,
    _parse_numbers_reference,
    _split_lists_reference,
    parse_numbers,
    split_lists,
)


def _bits(values) -> np.ndarray:
    """Values as their IEEE bit patterns: equal means identical, signed zeros and all."""
    return np.asarray(values, dtype=np.float64).view(np.int64)


def _assert_same(parsed, expected) -> None:
    np.testing.assert_array_equal(parsed.tokens_per_line, expected.tokens_per_line)
    assert parsed.tokens_per_line.dtype == np.int64 and parsed.values.dtype == np.float64
    nan = np.isnan(expected.values)
    np.testing.assert_array_equal(np.isnan(parsed.values), nan)
    np.testing.assert_array_equal(_bits(parsed.values[~nan]), _bits(expected.values[~nan]))
    assert parsed.bad == expected.bad


def _check_tokens(tokens: list[bytes]) -> None:
    """The tokens, seven to a line, parse bit-identically to float() and the reference."""
    data = b"\n".join(b" ".join(tokens[i:i + 7]) for i in range(0, len(tokens), 7)) + b"\n"
    parsed = parse_numbers(data)
    _assert_same(parsed, _parse_numbers_reference(data))
    np.testing.assert_array_equal(_bits(parsed.values), _bits([float(t) for t in tokens]))


# --------------------------------------------------------------------------
# Values.
# --------------------------------------------------------------------------


def _random_doubles(rng: np.random.Generator, count: int) -> np.ndarray:
    """Doubles of every magnitude: uniform bit patterns (finite), and ordinary scales."""
    bits = rng.integers(0, 0x7FF0000000000000, count, dtype=np.int64)
    wide = bits.view(np.float64) * rng.choice([-1.0, 1.0], count)
    plain = rng.normal(0, 1, count) * 10.0 ** rng.integers(-8, 9, count)
    return np.concatenate([wide, plain])


@pytest.mark.parametrize("fmt", ["%r", "%.17g", "%.18e", "%.15g", "%.9g", "%.6f", "%g", "%.3e", "%.0f", "%.25e", "%.40g"])
def test_random_doubles_in_many_formats_parse_exactly_like_float(fmt):
    rng = np.random.default_rng(zlib.crc32(fmt.encode()))
    values = _random_doubles(rng, 1500)
    if fmt == "%.0f":
        values = values[np.abs(values) < 1e300]  # keep the lines short
    tokens = [(repr(float(v)) if fmt == "%r" else fmt % v).encode() for v in values]
    _check_tokens(tokens)


def test_random_integers_and_decimals_in_every_spelling():
    rng = np.random.default_rng(3)
    tokens = []
    for _ in range(3000):
        digits = "".join(rng.choice(list("0123456789"), rng.integers(1, 24)))
        point = rng.integers(0, len(digits) + 1)
        body = rng.choice([digits, digits[:point] + "." + digits[point:], digits + ".", "." + digits])
        sign = rng.choice(["", "+", "-"])
        exponent = rng.choice(["", f"e{rng.integers(-30, 30)}", f"E+{rng.integers(0, 400)}", f"e-{rng.integers(0, 400)}"])
        tokens.append(f"{sign}{body}{exponent}".encode())
    _check_tokens(tokens)


@pytest.mark.parametrize(
    "token",
    [
        "0", "-0", "+0", "0.0", "-0.0", "0e0", "-0e-999", "00012", "5.", ".5", "+.5", "-5.", "1.e3", "1E+05", "1e-05",
        "9007199254740992", "9007199254740993", "9007199254740995", "18446744073709551615", "18446744073709551616",
        "1e22", "1e23", "123456789012345678e10", "1.7976931348623157e308", "1.7976931348623158e308", "1.8e308",
        "1e309", "2.2250738585072011e-308", "2.2250738585072014e-308", "4.9406564584124654e-324", "5e-324",
        "2.4703282292062327e-324", "2.4703282292062328e-324", "3e-324", "1e-400", "-1e-400",
        # Exactly halfway between doubles, then just above: round to even, then up.
        "9007199254740993.0000000000000000000", "9007199254740993.0000000000000000001",
        "0.1000000000000000055511151231257827021181583404541015625", "0.30000000000000004",
        "000000000000000000000000000001.5", "0.000000000000000000000000000001", "1.00000000000000000000000000",
        "123456789012345678901234567890e-30", "7.2057594037927933e16", "2.0000000000000004440892098500626161694526672363281250",
        "nan", "NaN", "-nan", "+NAN", "inf", "-inf", "+Inf", "INF", "infinity", "-Infinity", "iNfInItY",
    ],
)
def test_edge_case_tokens_parse_exactly_like_float(token):
    _check_tokens([token.encode()])


def test_halfway_and_near_halfway_decimals_round_like_float():
    # Midpoints between neighbouring doubles, written exactly and rounded to
    # 16 to 25 digits: the hardest inputs for correct rounding.
    rng = np.random.default_rng(11)
    tokens = []
    with localcontext() as context:
        context.prec = 1200  # a double or a midpoint has at most ~770 significant digits
        for value in _random_doubles(rng, 300):
            up = np.nextafter(value, np.inf)
            if value == 0 or not math.isfinite(up):
                continue
            midpoint = (Decimal(float(value)) + Decimal(float(up))) / 2
            tokens += [format(midpoint, "e").encode()] + [f"{midpoint:.{d}e}".encode() for d in (15, 16, 18, 19, 24)]
            tokens.append(f"{Decimal(float(value)):.30e}".encode())
    _check_tokens(tokens)


# --------------------------------------------------------------------------
# Layout: whitespace, lines, offsets.
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "values", "counts"),
    [
        (b"", [], [0]),
        (b"\n", [], [0, 0]),
        (b"  \t \r\n\n", [], [0, 0, 0]),
        (b"1 2 3", [1, 2, 3], [3]),
        (b"1 2 3\n", [1, 2, 3], [3, 0]),
        (b"1\t2  3   \r\n\r\n-4 +5e1\r\n", [1, 2, 3, -4, 50], [3, 0, 2, 0]),
        (b"\n\n 7 \n\x0b8\x0c\n", [7, 8], [0, 0, 1, 1, 0]),
    ],
    ids=["empty", "newline", "blank-lines", "no-final-newline", "final-newline", "crlf-tabs-trailing", "vt-ff"],
)
def test_tokens_per_line_count_every_line(data, values, counts):
    parsed = parse_numbers(data)
    assert parsed.values.tolist() == values and parsed.tokens_per_line.tolist() == counts and parsed.bad is None
    _assert_same(parsed, _parse_numbers_reference(data))


def test_random_layouts_match_the_reference():
    rng = np.random.default_rng(7)
    separators = [b" ", b"  ", b"\t", b" \t ", b"\r"]
    for _ in range(40):
        lines = []
        for _ in range(rng.integers(0, 60)):
            count = rng.integers(0, 6)
            numbers = [f"{v:.{rng.integers(0, 12)}f}".encode() for v in rng.normal(0, 100, count)]
            line = b"".join(n + separators[rng.integers(len(separators))] for n in numbers)
            lines.append(separators[rng.integers(len(separators))] * rng.integers(0, 2) + line)
        ending = [b"\n", b"\r\n"][rng.integers(2)]
        data = ending.join(lines) + ending * rng.integers(0, 3)
        _assert_same(parse_numbers(data), _parse_numbers_reference(data))


def test_start_skips_a_header_and_lines_count_from_it():
    data = b"header 1 x\n1 2\n\n3 4 5\n"
    start = data.index(b"\n") + 1
    parsed = parse_numbers(data, start=start)
    assert parsed.values.tolist() == [1, 2, 3, 4, 5] and parsed.tokens_per_line.tolist() == [2, 0, 3, 0]
    _assert_same(parsed, _parse_numbers_reference(data, start=start))
    assert parse_numbers(data, start=len(data)).tokens_per_line.tolist() == [0]
    with pytest.raises(ValueError, match="outside the data"):
        parse_numbers(data, start=len(data) + 1)


def test_many_long_tokens_are_exact_after_the_python_fallback():
    # More than 19 digits whose dropped digits decide the rounding: halfway
    # cases of 2**53 + 1 (the kernel hands these to float()).
    tokens = [b"9007199254740993" + b"0" * 20 + str(k).encode() for k in range(1, 300)]
    tokens += [b"9007199254740993" + b"0" * k for k in range(4, 30)]
    _check_tokens(tokens)


# --------------------------------------------------------------------------
# Bad tokens.
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "token",
    [b"abc", b"1_0", b"0x10", b"1e", b"e5", b".", b"-", b"+", b"+-1", b"--1", b"1e+", b"1.5f", b"-.e1", b".e1",
     b"1..2", b"1.2.3", b"nan(1)", b"-.nan", b"infinit", b"infinityy", b"nana", b"1,5", b"1-2", b"\xc2\xa01", b"\x00"],
)
def test_bad_token_is_reported_with_its_line_like_the_reference(token):
    data = b"1 2 3\n\n4 " + token + b" 6\n7 8 9\n"
    parsed = parse_numbers(data, strict=False)
    assert parsed.bad is not None
    assert (parsed.bad.index, parsed.bad.line, parsed.bad.text) == (4, 2, token)
    assert data[parsed.bad.offset:].startswith(token)
    _assert_same(parsed, _parse_numbers_reference(data))
    # Parsing goes on after it: complete line counts for the caller's checks.
    assert parsed.tokens_per_line.tolist() == [3, 0, 3, 3, 0] and parsed.values[-1] == 9
    with pytest.raises(NumberSyntaxError, match=r"line 3: expected a number") as error:
        parse_numbers(data)
    assert error.value.bad == parsed.bad


def test_first_bad_token_is_the_one_reported_and_lines_count_from_start():
    data = b"skip me\n1 2\n3 x y\n\nz\n"
    start = data.index(b"\n") + 1
    parsed = parse_numbers(data, start=start, strict=False)
    assert (parsed.bad.index, parsed.bad.line, parsed.bad.text) == (3, 1, b"x")
    _assert_same(parsed, _parse_numbers_reference(data, start=start))


def test_bad_token_at_the_very_end_without_newline():
    parsed = parse_numbers(b"1 2 3e", strict=False)
    assert (parsed.bad.index, parsed.bad.line, parsed.bad.text) == (2, 0, b"3e")


# --------------------------------------------------------------------------
# Length-prefixed lists.
# --------------------------------------------------------------------------


def test_split_lists_matches_the_reference_on_random_lists():
    rng = np.random.default_rng(5)
    for _ in range(50):
        lines = []
        for _ in range(rng.integers(0, 40)):
            length = int(rng.integers(0, 5))
            kind = rng.random()
            if kind < 0.05:
                lines.append([])
            elif kind < 0.1:
                lines.append([length + rng.choice([1, -1, 0.5, np.nan])] + list(rng.normal(size=length)))
            else:
                lines.append([length] + list(rng.integers(0, 1000, length)))
        values = np.array([v for line in lines for v in line], dtype=np.float64)
        counts = np.array([len(line) for line in lines], dtype=np.int64)
        got, expected = split_lists(values, counts), _split_lists_reference(values, counts)
        np.testing.assert_array_equal(got[0], expected[0])
        np.testing.assert_array_equal(got[1], expected[1])
        assert got[2:] == expected[2:]


def test_split_lists_reports_the_first_empty_and_wrong_lines():
    values = np.array([1, 5, 0, 3, 1, 2, 2, 7, 8], dtype=np.float64)
    lengths, items, empty, wrong = split_lists(values, np.array([2, 1, 0, 3, 3, 0]))
    assert lengths.tolist() == [1, 0, 0, 0, 2, 0] and items.tolist() == [5, 7, 8]
    assert (empty, wrong) == (2, 3)
    with pytest.raises(ValueError, match="adds up to"):
        split_lists(values, np.array([2]))
