"""Run-length decoding of SLC slices, compiled (a slice can hold a million short runs)."""

from __future__ import annotations

import numba

__all__ = ["decode_slices"]


@numba.njit(cache=True, nogil=True, boundscheck=False)
def decode_slices(raw, starts, sizes, out):  # pragma: no cover - compiled
    """Decode each slice's run-length code into its row of ``out``.

    The SLC code is a series of packets, each a byte ``c`` and what follows it: ``c & 0x7F``
    literal bytes when ``c & 0x80`` is set, else one byte repeated ``c & 0x7F`` times; a
    count of 0 ends the slice. A slice whose code stops short of its voxels leaves the
    rest of its row as it was; a code longer than the row, or a packet cut off by the
    slice's end, is read as far as both go.

    Parameters
    ----------
    raw : (B,) uint8
        The file's bytes.
    starts, sizes : (nz,) int64
        Where each slice's code starts in ``raw`` and its length in bytes (inside ``raw``).
    out : (nz, ny * nx) uint8
        The slices' voxels, written in place.
    """
    cap = out.shape[1]
    for z in range(starts.shape[0]):
        i = starts[z]
        end = starts[z] + sizes[z]
        n = 0
        while i < end and n < cap:
            c = raw[i]
            count = c & 0x7F
            if count == 0:
                break
            if c & 0x80:  # literal bytes
                stop = min(i + 1 + count, end)
                for t in range(i + 1, stop):
                    if n < cap:
                        out[z, n] = raw[t]
                        n += 1
                i += 1 + count
            else:  # one byte repeated
                if i + 1 >= end:
                    break
                v = raw[i + 1]
                for _ in range(count):
                    if n < cap:
                        out[z, n] = v
                        n += 1
                i += 2
