"""Decoding many CDR messages of one flattened layout, compiled (the kernel behind
:func:`.cdr.decode_batch`).

One pass over the messages walks each one's fields (strings move the offsets of what follows),
checks it and copies the wanted fields into two row-per-message matrices: floating fields into
``floats`` (float64) and integer fields into ``ints`` (int64; a string as the offset of its
bytes in buf and its length without the NUL). Only the messages that pass are written, one
after the other, so the matrices' first rows are the decoded messages in input order. The
kernel lets go of the GIL: the first filter pass runs on the other core while a bag is read.

A message passes when it is little-endian (``00 01`` encapsulation), at least header + 12 bytes
long, lies inside buf, every string length is between 1 and the payload size and inside the
payload, and its fields end inside the payload. What does not pass goes to the generic
deserializer (:mod:`.bagdecode`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.jit import kernel

# field kinds, by code: their size in bytes (STR: a uint32 length, then the bytes and a NUL)
STR, I1, U1, U2, I4, U4, F8 = range(7)
KIND_CODES = {"str": STR, "i1": I1, "u1": U1, "u2": U2, "i4": I4, "u4": U4, "f8": F8}
_KIND_SIZE = np.array([4, 1, 1, 2, 4, 4, 8], dtype=np.int64)
# what an ints column of the copy plan holds besides an integer field: a string's bytes'
# offset in buf (the message's start + src) or its length without the NUL (src itself)
_AT, _LENGTH = 7, 8


@kernel(nogil=True)
def decode_k(
    buf: NDArray[np.uint8],
    starts: NDArray[np.int64],
    sizes: NDArray[np.int64],
    kinds: NDArray[np.int64],
    counts: NDArray[np.int64],
    cols: NDArray[np.int64],
    floats: NDArray[np.float64],
    ints: NDArray[np.int64],
    ok: NDArray[np.bool_],
) -> int:
    """Decode the messages whose payloads (at the encapsulation header) are
    ``buf[starts[m] : starts[m] + sizes[m]]``.

    kinds, counts, cols: per field of the layout in order, its kind code (:data:`KIND_CODES`),
    element count and first column in ``floats`` (f8) or ``ints`` (other kinds; a string takes
    two: offset and length), -1 for a field not wanted. ok[m] is set for every message; the
    rows of the k messages that pass are floats[:k] and ints[:k]. Returns k.

    The fields' offsets depend on the strings' lengths only, which a bag's messages of one
    topic nearly always share: a message whose length words equal the last walked message's
    is copied by that message's plan (source offsets per column) after one look at its
    length words; any other is walked field by field.
    """
    nf = kinds.shape[0]
    offs = np.empty(nf, dtype=np.int64)  # the walked message's field offsets from its start
    f_src = np.empty(floats.shape[1], dtype=np.int64)  # the copy plan: source offset per column
    i_src = np.empty(ints.shape[1], dtype=np.int64)
    i_kind = np.empty(ints.shape[1], dtype=np.int64)
    n_str = 0
    for j in range(nf):
        n_str += kinds[j] == STR
    str_at = np.empty(n_str, dtype=np.int64)  # the plan's length words: offset and value
    str_len = np.empty(n_str, dtype=np.int64)
    end = -1  # the plan's payload length (-1: no plan yet)
    nbuf = buf.shape[0]
    k = 0
    for m in range(starts.shape[0]):
        start, size = starts[m], sizes[m]
        good = size >= 16 and start >= 0 and start + size <= nbuf
        good = good and buf[start] == 0 and buf[start + 1] == 1
        if good:
            same = end >= 0 and end <= size
            for i in range(n_str):
                same = same and _le(buf, start + str_at[i], 4) == str_len[i]
            if not same:
                end = _walk(buf, start, size, kinds, counts, offs)
                good = end >= 0
                if good:
                    _plan(buf, start, kinds, counts, cols, offs, f_src, i_src, i_kind,
                          str_at, str_len)  # fmt: skip
        ok[m] = good
        if not good:
            continue
        for c in range(f_src.shape[0]):
            floats[k, c] = _f8(buf, start + f_src[c])
        for c in range(i_src.shape[0]):
            ints[k, c] = _integer(buf, start, i_src[c], i_kind[c])
        k += 1
    return k


@kernel
def _walk(
    buf: NDArray[np.uint8],
    start: int,
    size: int,
    kinds: NDArray[np.int64],
    counts: NDArray[np.int64],
    offs: NDArray[np.int64],
) -> int:
    """The payload at buf[start] of ``size`` bytes walked field by field: each field's offset
    from start into offs (a string's: its length word's); returns the payload length its
    fields take, or -1 where a string length is not between 1 and size, or the fields do not
    end inside the payload."""
    pos = 0  # CDR alignment is relative to the first byte after the 4-byte header
    for j in range(kinds.shape[0]):
        step = _KIND_SIZE[kinds[j]]
        pos = (pos + step - 1) & ~(step - 1)
        offs[j] = 4 + pos
        if kinds[j] == STR:
            if 4 + pos + 4 > size:
                return -1
            n = np.int64(_le(buf, start + 4 + pos, 4))
            if n < 1 or n > size:
                return -1
            pos += 4 + n
        else:
            pos += step * counts[j]
    return 4 + pos if 4 + pos <= size else -1


@kernel
def _plan(
    buf: NDArray[np.uint8],
    start: int,
    kinds: NDArray[np.int64],
    counts: NDArray[np.int64],
    cols: NDArray[np.int64],
    offs: NDArray[np.int64],
    f_src: NDArray[np.int64],
    i_src: NDArray[np.int64],
    i_kind: NDArray[np.int64],
    str_at: NDArray[np.int64],
    str_len: NDArray[np.int64],
) -> None:
    """The copy plan of the message at buf[start] walked into offs (:func:`_walk`)."""
    s = 0
    for j in range(kinds.shape[0]):
        kind, c = kinds[j], cols[j]
        if kind == STR:
            n = np.int64(_le(buf, start + offs[j], 4))
            str_at[s], str_len[s] = offs[j], n
            s += 1
            if c >= 0:
                i_src[c], i_kind[c] = offs[j] + 4, _AT
                i_src[c + 1], i_kind[c + 1] = n - 1, _LENGTH
        elif c >= 0:
            for i in range(counts[j]):
                at = offs[j] + _KIND_SIZE[kind] * i
                if kind == F8:
                    f_src[c + i] = at
                else:
                    i_src[c + i], i_kind[c + i] = at, kind


@kernel
def _integer(buf: NDArray[np.uint8], start: int, src: int, kind: int) -> int:
    """An ints column of the message at buf[start] by its plan (source offset, kind)."""
    if kind == _LENGTH:
        return src
    if kind == _AT:
        return start + src
    if kind == I1:
        return np.uint8(buf[start + src]).view(np.int8)
    if kind == U1:
        return buf[start + src]
    if kind == U2:
        return _le(buf, start + src, 2)
    if kind == I4:
        return np.uint32(_le(buf, start + src, 4)).view(np.int32)
    return _le(buf, start + src, 4)


@kernel
def _le(buf: NDArray[np.uint8], p: int, nbytes: int) -> np.uint64:
    """The ``nbytes`` bytes at buf[p] as a little-endian unsigned integer (for 8, the
    compiler makes it one load)."""
    v = np.uint64(buf[p])
    for b in range(1, nbytes):
        v |= np.uint64(buf[p + b]) << np.uint64(8 * b)
    return v


@kernel
def _f8(buf: NDArray[np.uint8], p: int) -> float:
    """The little-endian float64 at buf[p] (written out so that the compiler makes it one
    load)."""
    v = np.uint64(buf[p]) | (np.uint64(buf[p + 1]) << np.uint64(8))
    v |= (np.uint64(buf[p + 2]) << np.uint64(16)) | (np.uint64(buf[p + 3]) << np.uint64(24))
    v |= (np.uint64(buf[p + 4]) << np.uint64(32)) | (np.uint64(buf[p + 5]) << np.uint64(40))
    v |= (np.uint64(buf[p + 6]) << np.uint64(48)) | (np.uint64(buf[p + 7]) << np.uint64(56))
    return np.uint64(v).view(np.float64)
