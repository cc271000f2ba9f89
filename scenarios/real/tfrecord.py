"""TFRecord files without TensorFlow: the framing, its CRC-32C checks, a reader and a writer.

Framing
    A TFRecord file is a sequence of records, each::

        uint64  length         little endian, the payload's byte count
        uint32  masked_crc32c(length's 8 bytes)
        bytes   payload        ``length`` bytes
        uint32  masked_crc32c(payload)

    with ``masked(crc) = ((crc >> 15) | (crc << 17)) + 0xa282ead8`` (mod 2^32) and CRC-32C
    the Castagnoli CRC (reflected polynomial ``0x82F63B78``, initial value and final XOR
    ``0xFFFFFFFF``; ``crc32c(b"123456789") == 0xE3069283``).

Checks
    :func:`iter_records` checks every header CRC and (by default) every payload CRC. A bad
    CRC, a record cut short by the end of the file, or a length over ``max_bytes`` is one
    :class:`~scenarios.dataset.DatasetError` naming the file and the record index (from 0),
    the byte offset of the record and which check failed (the length's CRC or the
    payload's).

CRC-32C
    :func:`crc32c` is a table-driven CRC: short inputs go through a 256-entry table byte by
    byte (plain Python); long ones are cut into equal chunks whose CRC registers are
    advanced together (numpy, four bytes a step with four tables, "slicing by 4"), then
    joined, since the CRC register is linear over GF(2): the register of ``A + B`` is the
    register of ``A`` advanced over ``len(B)`` zero bytes XOR the register of ``B`` from 0.
"""

from __future__ import annotations

import functools
import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "MAX_RECORD_BYTES",
    "Record",
    "crc32c",
    "masked_crc32c",
    "iter_records",
    "read_record",
    "write_records",
]

_POLY = 0x82F63B78
_MASK32 = 0xFFFFFFFF
_MASK_DELTA = 0xA282EAD8
#: the largest payload read (a Waymo Open Motion Scenario is about 1 MB; this bounds the
#: memory a corrupt or hostile length can ask for)
MAX_RECORD_BYTES = 256 * 2**20
#: inputs at least this long go through the numpy path of :func:`crc32c`
_VECTOR_BYTES = 2048


def _chunk(n: int) -> int:
    """Bytes per chunk of the numpy path for ``n`` bytes (a multiple of 4; measured best)."""
    return 32 if n < 2**16 else 64 if n < 2**19 else 128


def _make_table() -> list[int]:
    out = []
    for n in range(256):
        c = n
        for _ in range(8):
            c = (c >> 1) ^ _POLY if c & 1 else c >> 1
        out.append(c)
    return out


_TABLE = _make_table()
# slicing by 4: _T4[k][b] is the register contribution of byte b followed by k zero bytes
_T4 = np.zeros((4, 256), np.uint32)
_T4[0] = _TABLE
for _k in range(1, 4):
    _T4[_k] = (_T4[_k - 1] >> np.uint32(8)) ^ _T4[0][_T4[_k - 1] & np.uint32(0xFF)]


def _update_bytes(reg: int, data) -> int:
    """The CRC register after ``data`` from ``reg`` (one table lookup a byte)."""
    t = _TABLE
    for b in data:
        reg = t[(reg ^ b) & 0xFF] ^ (reg >> 8)
    return reg


@functools.lru_cache(maxsize=64)
def _shift_tables(n: int) -> np.ndarray:
    """``(4, 256)`` tables of the linear map "advance the register over ``n`` zero bytes":
    its value on a register is the XOR of ``tables[k][(reg >> 8 k) & 0xFF]``."""

    # the map's value on each of the 32 unit registers, by squaring the one-zero-byte map
    def apply(cols, r):
        out = 0
        k = 0
        while r:
            if r & 1:
                out ^= cols[k]
            r >>= 1
            k += 1
        return out

    one = [_update_bytes(1 << k, b"\0") for k in range(32)]  # one zero byte
    result = [1 << k for k in range(32)]  # identity
    power = one
    while n:
        if n & 1:
            result = [apply(power, c) for c in result]
        power = [apply(power, c) for c in power]
        n >>= 1
    tab = [[0] * 256 for _ in range(4)]
    for k in range(4):
        row = tab[k]
        for v in range(1, 256):  # v = its lowest set bit + the rest (already computed)
            low = v & -v
            row[v] = row[v ^ low] ^ result[8 * k + low.bit_length() - 1]
    return np.array(tab, np.uint32)


def _shift(reg: np.ndarray, n: int) -> np.ndarray:
    t = _shift_tables(n)
    return (
        t[0][reg & 0xFF]
        ^ t[1][(reg >> np.uint32(8)) & 0xFF]
        ^ t[2][(reg >> np.uint32(16)) & 0xFF]
        ^ t[3][reg >> np.uint32(24)]
    )


def _update_vector(reg: int, data: memoryview) -> int:
    """The register after ``data`` (at least a few chunks long) from ``reg``, numpy path."""
    c = _chunk(len(data))
    m = len(data) // c
    words = np.frombuffer(data[: m * c], "<u4").reshape(m, c // 4)
    state = np.zeros(m, np.uint32)
    state[0] = reg
    t0, t1, t2, t3 = _T4[3], _T4[2], _T4[1], _T4[0]
    for j in range(c // 4):
        x = state ^ words[:, j]
        state = (
            t0[x & 0xFF]
            ^ t1[(x >> np.uint32(8)) & 0xFF]
            ^ t2[(x >> np.uint32(16)) & 0xFF]
            ^ t3[x >> np.uint32(24)]
        )
    # join the chunks pairwise: (left, right) -> left advanced over right's length ^ right;
    # a zero register in front of an odd count changes nothing (only left ones are shifted)
    span = c
    while len(state) > 1:
        if len(state) % 2:
            state = np.concatenate([np.zeros(1, np.uint32), state])
        state = _shift(state[0::2], span) ^ state[1::2]
        span *= 2
    return _update_bytes(int(state[0]), data[m * c :])


def crc32c(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-32C (Castagnoli) of ``data``; ``crc`` continues a CRC of earlier bytes
    (``crc32c(a + b) == crc32c(b, crc32c(a))``)."""
    mv = memoryview(data).cast("B")
    reg = crc ^ _MASK32
    if len(mv) >= _VECTOR_BYTES:
        reg = _update_vector(reg, mv)
    else:
        reg = _update_bytes(reg, mv)
    return reg ^ _MASK32


def masked_crc32c(data: bytes | bytearray | memoryview) -> int:
    """The TFRecord form of :func:`crc32c`: rotated right by 15 bits plus ``0xa282ead8``."""
    c = crc32c(data)
    return (((c >> 15) | (c << 17)) + _MASK_DELTA) & _MASK32


@dataclass(frozen=True)
class Record:
    """One record of a TFRecord file: its index (from 0), byte offset and payload."""

    index: int
    offset: int
    payload: bytes


def _error(path, index: int, offset: int, message: str):
    from scenarios.dataset import DatasetError

    return DatasetError(f"{path}:record {index}", f"{message} (record at byte {offset:,})")


def _read_one(f, path, index: int, offset: int, size: int, check: bool, max_bytes: int):
    """The record at ``offset`` (the file positioned there), or None at a clean end."""
    head = f.read(12)
    if not head:
        return None
    if len(head) < 12:
        raise _error(path, index, offset, f"truncated: the header has {len(head)} of 12 bytes")
    (length,) = struct.unpack("<Q", head[:8])
    (stored,) = struct.unpack("<I", head[8:])
    got = masked_crc32c(head[:8])
    if stored != got:
        raise _error(
            path,
            index,
            offset,
            f"the length's CRC fails (stored 0x{stored:08x}, computed 0x{got:08x}): not a "
            "TFRecord file, or a corrupt header",
        )
    if length > max_bytes:
        raise _error(
            path, index, offset, f"length {length:,} bytes is over the limit of {max_bytes:,}"
        )
    left = size - offset - 12
    if length + 4 > left:
        raise _error(
            path,
            index,
            offset,
            f"truncated: the header announces {length:,} payload bytes and a 4-byte CRC, "
            f"the file has {max(left, 0):,} more",
        )
    payload = f.read(length)
    tail = f.read(4)
    if len(payload) < length or len(tail) < 4:  # the file shrank while we read it
        raise _error(path, index, offset, "truncated while reading the payload")
    if check:
        (stored,) = struct.unpack("<I", tail)
        got = masked_crc32c(payload)
        if stored != got:
            raise _error(
                path,
                index,
                offset,
                f"the payload's CRC fails (stored 0x{stored:08x}, computed 0x{got:08x}): "
                "a corrupt record",
            )
    return payload


def _open(path):
    from scenarios.files import check_input_file

    p = check_input_file(path, str(path), max_bytes=None)
    return p, open(p, "rb"), os.stat(p).st_size


def iter_records(
    path: str | os.PathLike,
    *,
    check_crc: bool = True,
    max_bytes: int = MAX_RECORD_BYTES,
) -> Iterator[Record]:
    """Every record of the TFRecord file ``path`` in order (errors: the module docstring).
    ``check_crc=False`` skips the payload CRCs (the length CRCs are always checked)."""
    p, f, size = _open(path)
    with f:
        index, offset = 0, 0
        while True:
            payload = _read_one(f, p, index, offset, size, check_crc, max_bytes)
            if payload is None:
                return
            yield Record(index, offset, payload)
            offset += 16 + len(payload)
            index += 1


def read_record(
    path: str | os.PathLike,
    offset: int,
    index: int = 0,
    *,
    check_crc: bool = True,
    max_bytes: int = MAX_RECORD_BYTES,
) -> bytes:
    """The payload of the record at byte ``offset`` of ``path`` (``index`` names it in
    errors); an offset at the end of the file is a truncated record."""
    p, f, size = _open(path)
    with f:
        f.seek(offset)
        payload = _read_one(f, p, index, offset, size, check_crc, max_bytes)
    if payload is None:
        raise _error(p, index, offset, "truncated: no record at this offset (end of file)")
    return payload


def write_records(path: str | os.PathLike, payloads: Iterable[bytes]) -> Path:
    """Write ``payloads`` as a TFRecord file at ``path`` (atomically); returns the path."""
    from scenarios.files import write_atomic

    parts = []
    for data in payloads:
        data = bytes(data)
        head = struct.pack("<Q", len(data))
        parts += [
            head,
            struct.pack("<I", masked_crc32c(head)),
            data,
            struct.pack("<I", masked_crc32c(data)),
        ]
    return write_atomic(path, b"".join(parts))
