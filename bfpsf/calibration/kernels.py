"""What the compiled (numba) kernels of the flat-pair mask and covariances share.

The kernels look for rare pixels (defects, clipping candidates) in rows of millions of values.
They compare a whole row at once into a byte row of flags, which vectorises, and then visit
only the flagged positions: `flagged_positions` reads the flags 8 bytes at a time and skips
the words that are all zero.
"""

import numba
import numpy as np

#: Floating-point flags of the kernels: sums may be reassociated (so they vectorise); NaN and
#: inf keep their meaning (no 'nnan' / 'ninf').
FASTMATH = {"reassoc", "contract", "nsz", "arcp"}


@numba.njit(cache=True, nogil=True)
def flag_row(size):
    """A byte row of flags for rows of ``size`` values, padded to whole 8-byte words."""
    return np.zeros(8 * ((size + 7) // 8), dtype=np.uint8)


@numba.njit(cache=True, nogil=True, inline="always")
def flagged_positions(flags, size, out):
    """Write the positions j < ``size`` where ``flags[j]`` is set to ``out``, increasing;
    return their number. ``flags`` is a `flag_row`."""
    words = flags.view(np.uint64)
    count = 0
    for word in range(words.size):
        if words[word] == 0:
            continue
        for j in range(8 * word, min(size, 8 * word + 8)):
            if flags[j]:
                out[count] = j
                count += 1
    return count
