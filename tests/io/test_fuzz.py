"""Readers under attack: random bytes, truncated and mutated real files.

The only outcomes allowed: valid frames, or rangesurf's own `FormatError`
naming the file. Property-based (hypothesis) with a bounded number of
examples per reader so that ``make test`` stays fast; the long runs are
``fuzz/fuzz_readers.py`` (atheris).
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis (test extra) is needed for the property tests")
from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import rangesurf as rs  # noqa: E402
from rangesurf.io import FormatError  # noqa: E402

# RANGESURF_FUZZ_EXAMPLES raises the count for a longer local run.
EXAMPLES = settings(max_examples=int(os.environ.get("RANGESURF_FUZZ_EXAMPLES", "40")), deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])
SUFFIXES = (".3d", ".ply", ".pcd", ".npz", ".npy", ".png")


def _seed_files() -> dict[str, bytes]:
    """One small valid file per format, written by rangesurf's own writers (and the text variants)."""
    frames, _ = rs.simulate.simulate_sequence("arena", "sr3000", 1, seed=0)
    frame = frames[0]
    seeds = {}
    with tempfile.TemporaryDirectory() as folder:
        for suffix in (".ply", ".pcd", ".npz", ".3d", ".png"):
            (path,) = rs.save(Path(folder) / f"seed{suffix}", frame)
            seeds[suffix] = Path(path).read_bytes()
        np.save(Path(folder) / "seed.npy", frame.range)
        seeds[".npy"] = (Path(folder) / "seed.npy").read_bytes()
    return seeds


SEEDS = _seed_files()


def _read(data: bytes, suffix: str) -> None:
    """Read ``data`` as a file of ``suffix``: valid frames or a FormatError naming the file, nothing else."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"fuzzed{suffix}"
        path.write_bytes(data)
        try:
            frames = rs.load(path)
        except FormatError as error:
            assert "fuzzed" in str(error), f"error does not name the file: {error}"
            return
        for frame in frames:
            assert isinstance(frame, rs.RangeFrame)
            assert not np.isinf(frame.range).any()
            assert frame.range.shape == frame.rays.shape[:2]


@pytest.mark.parametrize("suffix", SUFFIXES)
@EXAMPLES
@given(data=st.binary(max_size=2048))
def test_random_bytes(suffix, data):
    _read(data, suffix)


@pytest.mark.parametrize("suffix", sorted(SEEDS))
@EXAMPLES
@given(fraction=st.floats(0.0, 1.0))
def test_truncated_files(suffix, fraction):
    seed = SEEDS[suffix]
    _read(seed[: int(len(seed) * fraction)], suffix)


@pytest.mark.parametrize("suffix", sorted(SEEDS))
@EXAMPLES
# Found by this test: a corrupted .npy header made numpy's tokenizer raise (now a FormatError).
@example(flips=[(0.0001, 0)])
@given(flips=st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.integers(0, 255)), min_size=1, max_size=8))
def test_mutated_bytes(suffix, flips):
    data = bytearray(SEEDS[suffix])
    for where, value in flips:
        data[int(where * len(data))] = value
    _read(bytes(data), suffix)


def _header_numbers(text: str) -> list[re.Match]:
    return list(re.finditer(rb"-?\d+(\.\d+)?".decode(), text))


@pytest.mark.parametrize("suffix", [suffix for suffix in (".ply", ".pcd", ".3d") if suffix in SEEDS])
@EXAMPLES
# Found by this test: a huge PCD VIEWPOINT overflowed the quaternion norm; a huge PLY element count
# was allocated before the file was checked; a value past float32 in a .3d file became Inf.
@example(choice=0.875, value="1e308")
@example(choice=0.984375, value="99999999999")
@example(choice=0.8125, value="1e308")
@given(choice=st.floats(0.0, 1.0, exclude_max=True),
       value=st.sampled_from(["0", "-1", "-7", "99999999999", "4294967296", "1e308", "nan", "inf", "3.5", "x"]))
def test_mutated_header_numbers(suffix, choice, value):
    """Grid sizes, point counts, field sizes and types replaced by hostile values (declared sizes far too large
    must fail before any huge allocation)."""
    seed = SEEDS[suffix]
    end = seed.find(b"end_header\n") + len(b"end_header\n") if suffix == ".ply" else seed.find(b"DATA")
    end = end if end > 0 else min(len(seed), 200)
    header = seed[:end].decode("latin-1")
    numbers = _header_numbers(header)
    if not numbers:
        return
    match = numbers[int(choice * len(numbers))]
    mutated = header[: match.start()] + value + header[match.end():]
    _read(mutated.encode("latin-1") + seed[end:], suffix)


def test_regression_binary_ply_with_an_infinite_coordinate(tmp_path):
    """Found by fuzz/fuzz_readers.py: a float turned into Inf reached the frame's checks as a ValueError."""
    path = tmp_path / "inf.ply"
    rs.save(path, rs.simulate.simulate_sequence("arena", "sr3000", 1, seed=0)[0][0])
    data = bytearray(path.read_bytes())
    body = data.index(b"end_header\n") + len(b"end_header\n")
    data[body: body + 4] = np.float32(np.inf).tobytes()  # the first vertex's x
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="inf.ply"):
        rs.load(path)


def test_regression_npz_with_an_unknown_zip_version(tmp_path):
    """Found by fuzz/fuzz_readers.py: zipfile raises NotImplementedError for a version it does not know."""
    path = tmp_path / "version.npz"
    rs.save(path, rs.simulate.simulate_sequence("arena", "sr3000", 1, seed=0)[0][0])
    data = bytearray(path.read_bytes())
    central = data.index(b"PK\x01\x02")
    data[central + 6: central + 8] = (122).to_bytes(2, "little")  # "version needed to extract": 12.2
    data[4:6] = (122).to_bytes(2, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="version.npz"):
        rs.load(path)


def _with_header(header: str) -> bytes:
    """A .npy file whose header dictionary is ``header`` (padded as numpy pads it), with no data."""
    text = header.ljust(118) + "\n"
    return b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text.encode("latin-1")


def test_regression_npy_with_a_shape_past_any_integer(tmp_path):
    """Found by fuzz/run_all.py: numpy overflowed a C long on the declared shape."""
    path = tmp_path / "huge.npy"
    path.write_bytes(_with_header("{'descr': '<f4', 'fortran_order': False, 'shape': (" + "9" * 40 + ", 10), }"))
    with pytest.raises(FormatError, match="huge.npy"):
        rs.load(path)


def test_regression_npz_with_an_encrypted_member(tmp_path):
    """Found by fuzz/run_all.py: zipfile raises RuntimeError for a member flagged as encrypted."""
    path = tmp_path / "locked.npz"
    rs.save(path, rs.simulate.simulate_sequence("arena", "sr3000", 1, seed=0)[0][0])
    data = bytearray(path.read_bytes())
    for marker in (b"PK\x03\x04", b"PK\x01\x02"):
        start = 0
        while (position := data.find(marker, start)) >= 0:
            flags_at = position + (6 if marker == b"PK\x03\x04" else 8)
            data[flags_at] |= 0x01  # general purpose bit 0: encrypted
            start = position + 4
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="locked.npz"):
        rs.load(path)


def test_regression_png_declaring_a_huge_image(tmp_path):
    """Found by fuzz/run_all.py: the decoder allocated what a hostile IHDR declared."""
    path = tmp_path / "huge.png"
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")

    header = (60000).to_bytes(4, "big") + (60000).to_bytes(4, "big") + bytes([16, 0, 0, 0, 0])
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))
    with pytest.raises(FormatError, match="huge.png.*IHDR"):
        rs.load(path)


def test_regression_npy_with_a_bytes_dtype(tmp_path):
    """Found by fuzz/run_all.py: a bytes literal as the dtype made numpy's header check raise TypeError."""
    path = tmp_path / "bytes.npy"
    path.write_bytes(_with_header("{'descr': b'<f4', 'fortran_order': False, 'shape': (2, 2), }") + bytes(16))
    with pytest.raises(FormatError, match="bytes.npy"):
        rs.load(path)


def test_regression_npz_with_a_member_that_is_not_an_array(tmp_path):
    """Found by fuzz/run_all.py: np.load returns raw bytes for a zip member that is not an .npy file."""
    import zipfile

    path = tmp_path / "member.npz"
    rs.save(path, rs.simulate.simulate_sequence("arena", "sr3000", 1, seed=0)[0][0])
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("range", b"not an array")
    with pytest.raises(FormatError, match="member.npz"):
        rs.load(path)
