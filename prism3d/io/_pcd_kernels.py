"""LZF decompression kernel for PCD ``binary_compressed`` data (numba)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def lzf_decompress(src: np.ndarray, out_len: int) -> tuple[np.ndarray, int]:
    """Decompress an LZF stream.

    Parameters
    ----------
    src : (N,) uint8
        The compressed bytes.
    out_len : int
        The expected decompressed size.

    Returns
    -------
    out : (out_len,) uint8
    status : int
        Bytes written, or -1 when the stream is corrupt (reference before the
        start of the output, or output/input overrun).

    Notes
    -----
    LZF control byte ``c``: ``c < 32`` copies ``c + 1`` literal bytes; otherwise
    a back reference of length ``(c >> 5) + 2`` (``+ next byte`` when ``c >> 5 == 7``)
    at distance ``((c & 31) << 8) + next byte + 1`` (Lehmann's liblzf format).
    """
    out = np.zeros(out_len, dtype=np.uint8)
    ip = 0
    op = 0
    n = src.shape[0]
    while ip < n:
        ctrl = np.int64(src[ip])
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if op + length > out_len or ip + length > n:
                return out, -1
            for i in range(length):
                out[op + i] = src[ip + i]
            op += length
            ip += length
        else:
            length = ctrl >> 5
            if length == 7:
                if ip >= n:
                    return out, -1
                length += np.int64(src[ip])
                ip += 1
            if ip >= n:
                return out, -1
            ref = op - ((ctrl & 31) << 8) - 1 - np.int64(src[ip])
            ip += 1
            length += 2
            if ref < 0 or op + length > out_len:
                return out, -1
            for i in range(length):
                out[op + i] = out[ref + i]
            op += length
    return out, op
