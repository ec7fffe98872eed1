"""Resource guards: estimate the memory and time a computation needs from its options and
inputs, and refuse it before allocating anything when the estimate exceeds the limit.

A command whose options ask for more than the machine has must not grow until the kernel kills
it (or, on a shared machine, kills another user's process), nor run for days: it refuses at
once, in one line naming the option, the estimate and the limit (`BFPSFResourceError`).

Limits:

* memory: ``BFPSF_MEMORY_LIMIT`` (bytes, or with a suffix K, M, G, T: ``8G``) when set; else
  the smaller of the memory the system has available now (``MemAvailable``) and what the
  address-space limit of this process (``ulimit -v``, RLIMIT_AS) leaves;
* time: ``BFPSF_TIME_LIMIT`` (seconds) when set, else `DEFAULT_TIME_LIMIT`.

The estimates are upper bounds measured on the code as it is (see each estimator); they err
on the side of a refusal only by a small factor.
"""

import os
import re
from contextlib import contextmanager

from .errors import BFPSFResourceError

__all__ = ["DEFAULT_TIME_LIMIT", "memory_limit", "time_limit", "check_settings", "check_memory",
           "check_time", "format_bytes", "psf_fit_cost", "check_psf_fit", "check_pixels",
           "resource_option", "check_flat_simulation", "check_spot_simulation"]

#: Default bound on the estimated run time of one computation, s (3 hours).
DEFAULT_TIME_LIMIT = 3 * 3600.0

#: Sustained floating-point rate assumed for the time estimates (one core; measured 1.5-3
#: GFLOP/s for the P0 fit's matrix products on the 2-core test machine), flop/s.
FLOP_RATE = 1.5e9

_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def format_bytes(count):
    """``'1.5 GiB'``-style text of a byte count."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(count) < 1024 or unit == "PiB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.3g} {unit}"
        count /= 1024.0
    return None  # not reached


def _parse_bytes(text):
    match = re.fullmatch(r"\s*([0-9.]+)\s*([KMGT]?)i?B?\s*", str(text), flags=re.IGNORECASE)
    if match is None:
        msg = f"BFPSF_MEMORY_LIMIT must be a number of bytes (e.g. 8G), got {text!r}"
        raise BFPSFResourceError(msg, text)
    return float(match.group(1)) * _UNITS[match.group(2).upper()]


def _meminfo(key):
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith(f"{key}:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def _address_space_left():
    """What RLIMIT_AS leaves this process, bytes (None: no limit)."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, OSError, ValueError):
        return None
    if soft == resource.RLIM_INFINITY:
        return None
    used = None
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith("VmSize:"):
                    used = float(line.split()[1]) * 1024
    except OSError:
        used = None
    return max(float(soft) - (used or 0.0), 0.0)


def memory_limit():
    """The memory a computation may allocate, bytes (module docstring), and where that limit
    comes from, for the message."""
    if os.environ.get("BFPSF_MEMORY_LIMIT"):
        return _parse_bytes(os.environ["BFPSF_MEMORY_LIMIT"]), "BFPSF_MEMORY_LIMIT"
    candidates = []
    available = _meminfo("MemAvailable")
    if available is not None:
        candidates.append((available, "memory available"))
    left = _address_space_left()
    if left is not None:
        candidates.append((left, "address-space limit (ulimit -v)"))
    if not candidates:
        return float("inf"), "no limit known"
    return min(candidates)


def time_limit():
    """The run time a computation may take, s (``BFPSF_TIME_LIMIT`` or the default)."""
    text = os.environ.get("BFPSF_TIME_LIMIT")
    if not text:
        return DEFAULT_TIME_LIMIT
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0:
        msg = f"BFPSF_TIME_LIMIT must be a positive number of seconds, got {text!r}"
        raise BFPSFResourceError(msg, text)
    return value


def check_settings():
    """Parse ``BFPSF_TIME_LIMIT`` and ``BFPSF_MEMORY_LIMIT`` when set: every command refuses a
    bad setting before any work, whether or not it estimates a cost."""
    time_limit()
    if os.environ.get("BFPSF_MEMORY_LIMIT"):
        memory_limit()


def check_memory(estimate, *, option, what):
    """Raise `BFPSFResourceError` if ``estimate`` bytes exceed `memory_limit`.

    ``option`` names what the user can change (e.g. ``'--grid 50 50'``), ``what`` the
    computation (e.g. ``'the P0 fit'``).
    """
    limit, source = memory_limit()
    if estimate > limit:
        msg = (f"{option}: {what} would need about {format_bytes(estimate)} of memory, more than "
               f"the {format_bytes(limit)} limit ({source}); use smaller values")
        raise BFPSFResourceError(msg, estimate)


def check_time(estimate, *, option, what):
    """Raise `BFPSFResourceError` if ``estimate`` seconds exceed `time_limit`."""
    limit = time_limit()
    if estimate > limit:
        msg = (f"{option}: {what} would take about {estimate / 3600:.3g} h, more than the "
               f"{limit / 3600:.3g} h limit (BFPSF_TIME_LIMIT, s); use smaller values")
        raise BFPSFResourceError(msg, estimate)


def psf_fit_cost(n_stars, size, oversampling, n_nodes, iterations):
    """(bytes, seconds) of `bfpsf.model.psf_fit.fit_psf`.

    Memory, in 8-byte values: the per-cell normal systems of the node update, about 3 copies
    of M^2 K^2 (M the oversampled side, K the nodes), the star-pair weights 2 N K^2, per star
    about 30 cut-out sides S^2 and 4 M^2, per node 20 M^2. Measured (peak RSS above the
    baseline) 31 MB for N = 100, K = 1; 100 MB for N = 400, K = 1; 500 MB for N = 100,
    K = 100; 143 MB for N = 400, K = 36 (size 25, oversampling 2): the estimate is 1.0-1.4
    times these.

    Time: per iteration 2 N K^2 M^2 + M^2 K^3 / 3 flop (the pair products and the solves) at
    `FLOP_RATE`, plus 1 ms per star; measured 4.2 s per iteration for N = K = 100.
    """
    if min(int(size), int(oversampling), int(n_nodes), int(iterations)) < 1:
        return 0.0, 0.0  # the fit itself refuses these, with its own message
    over = int(oversampling)
    side = int(size) * over + (1 - over % 2)
    cells = float(side) ** 2
    cutout = (int(size) + 2) ** 2
    nodes, stars = float(n_nodes), float(n_stars)
    values = (3 * cells * nodes**2 + 2 * stars * nodes**2 + 30 * stars * cutout
              + 4 * stars * cells + 20 * nodes * cells)
    flop = 2 * stars * nodes**2 * cells + cells * nodes**3 / 3
    seconds = (int(iterations) + 3) * (flop / FLOP_RATE + 1e-3 * stars)
    return 8.0 * values, seconds


def check_psf_fit(n_stars, size, oversampling, grid, iterations):
    """Refuse a P0 fit (`psf_fit_cost`) beyond the memory or time limit, naming the options
    (``--grid``, ``--oversampling``, ``--size``, ``--max-iterations``)."""
    nx, ny = (1, 1) if grid is None else (int(grid[0]), int(grid[1]))
    memory, seconds = psf_fit_cost(n_stars, size, oversampling, nx * ny, iterations)
    options = (f"--grid {nx} {ny}, " if grid is not None else "") + (
        f"--oversampling {oversampling}, --size {size}")
    stars = f" of {n_stars} stars" if n_stars else ""
    check_memory(memory, option=options, what=f"the P0 fit{stars}")
    check_time(seconds, option=f"{options}, --max-iterations {iterations}",
               what=f"the P0 fit{stars}")


def check_pixels(count, *, copies, option, what):
    """Refuse an image computation over ``count`` pixels holding ``copies`` float64 arrays of
    them at once beyond the memory limit."""
    check_memory(8.0 * float(count) * copies, option=option, what=what)


@contextmanager
def resource_option(option):
    """Within this block, a `BFPSFResourceError` names ``option`` (the user's option behind
    the library's parameter, e.g. ``--size 2001`` behind a stamp size of 2007)."""
    try:
        yield
    except BFPSFResourceError as error:
        msg = f"{option}: {error}"
        raise BFPSFResourceError(msg, error.value) from None


def check_flat_simulation(size, n_flats, nsteps, *, option):
    """Refuse a SiliconSensor flat simulation (`bfpsf.validation.simulate_flats`) beyond the
    limits: one flat holds about 48 float64 values per pixel (GalSim's pixel areas and
    boundaries; 14 MB more for 256^2 than 128^2 pixels, measured), and each increment costs
    3-6 us per pixel (measured on 2 cores; the lower value is used, so a refusal is sure)."""
    pixels = (float(size) + 10) ** 2  # the simulated margin
    check_memory(8.0 * 48 * pixels, option=option, what="simulating a flat")
    check_time(3e-6 * float(n_flats) * float(nsteps) * pixels, option=option,
               what=f"simulating {n_flats} flats")


def check_spot_simulation(n_per_level, peaks_e, fwhm, stamp_size, *, option):
    """Refuse a photon-shot spot series (`bfpsf.validation.simulate_spots`) beyond the limits:
    a spot of peak P and FWHM f holds about 1.13 f^2 P electrons (a Gaussian's), each photon
    costs at least 1e-7 s in SiliconSensor (0.3 s measured for a 2.7e6 e- spot), and every
    spot keeps about 8 float64 stamps."""
    spots = float(n_per_level) * len(peaks_e)
    photons = float(n_per_level) * 1.133 * float(fwhm) ** 2 * float(sum(peaks_e))
    check_memory(8.0 * 8 * spots * float(stamp_size) ** 2, option=option,
                 what=f"simulating {spots:.0f} spots")
    check_time(1e-7 * photons, option=option, what=f"shooting {photons:.3g} photons")
