"""The ``bfpsf`` command: a thin layer over the library (parse, call, write).

Each sub-command lives in its own module ``bfpsf.cli.<name>`` that defines
``add_parser(subparsers)`` (returning the sub-parser) and ``run(args)`` (returning an exit code).

Every command also takes the common options (`add_common_options`): ``--progress`` /
``--no-progress`` (default: on only when stderr is a terminal, so a log file never gets escape
codes), ``-v`` / ``-q`` (logging to stderr: warnings by default, ``-v`` info, ``-vv`` debug,
``-q`` errors only) and ``--threads N`` (default ``OMP_NUM_THREADS`` when set, else every CPU).

The modules of ``bfpsf.cli`` import most of the library inside their functions, when a command
runs, so that ``bfpsf --help`` does not load GalSim, photutils or matplotlib; at the top they
import only what their options and help texts need.
"""

import argparse
import contextlib
import importlib
import logging
import math
import os
import signal
import sys
import threading

from .. import __version__
from ..errors import BFPSFError, BFPSFValueError
from ..outputs import all_or_nothing

#: Sub-commands in data-flow order; each name is a module of this package.
COMMANDS = ["simulate", "calibrate", "measure", "slope", "psf", "photometry", "validate",
            "diagnose"]




def image_arguments(parser, verb, about="", after=""):
    """The star images and ``--amp`` of the commands that read them (measure, psf,
    photometry): ``verb`` names what ``--amp`` limits, ``about`` and ``after`` extend the
    images' help."""
    parser.add_argument("images", nargs="+", metavar="IMAGE.fits",
                        help=f"images in ADU{about}: bias-subtracted single-HDU, or one HDU "
                             f"per amplifier (EXTNAME, optional BIASSEC/DATASEC/DETSEC){after}")
    parser.add_argument("--amp", action="append", metavar="NAME",
                        help=f"{verb} only this amplifier (EXTNAME); repeatable")


def output_options(parser, *, json=True):
    """``--json`` (a JSON summary) and ``--overwrite`` (outputs are never replaced without it)
    of every command that writes files."""
    if json:
        parser.add_argument("--json", metavar="FILE", help="write a JSON summary")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")


#: Default of ``--saturation`` in the commands that read star images.
SATURATION_DEFAULT = ("default the header's SATURATE or a variant; the calibration's "
                      "linearity turnoff where lower")


def star_image_options(parser, *, saturation, wings=True, threshold=True, background=True,
                       sky_degree=True):
    """``--threshold`` (detection), ``--background``, ``--sky-degree`` and ``--saturation``
    of the commands that find stars in images: ``saturation`` says what the level does (its
    default is `SATURATION_DEFAULT`), ``wings`` whether the default sky masks the stars'
    wings too, ``threshold`` whether the command detects (``diagnose``'s own --threshold is a
    Delta BIC), ``background`` whether it takes a sky level (``measure`` fits its own),
    ``sky_degree`` whether it takes the degree of the sky surface."""
    if threshold:
        from ..measure.sources import DETECTION_THRESHOLD

        parser.add_argument("--threshold", type=positive_float, default=DETECTION_THRESHOLD,
                            help=f"detection threshold, RMS of the smoothed image (default "
                                 f"{DETECTION_THRESHOLD:g})")
    if background:
        parser.add_argument("--background", type=background_option, default=None,
                            metavar="ADU",
                            help="a known sky level of the images, ADU per pixel (0 for "
                                 "sky-subtracted images); default the sky surface of each "
                                 "image: a plane (degree 2, 3 or a spline where the sky is curved) "
                                 "fitted beyond the masked sources"
                                 + (" and the stars' wings" if wings else ""))
        if sky_degree:
            parser.add_argument("--sky-degree", type=sky_degree_option, default="auto",
                                metavar="auto|0-3|spline",
                                help="degree of the fitted sky surface of each image (default "
                                     "auto: a plane, or 2 or 3 where the sky pixels show a "
                                     "curved sky, or a bicubic spline with knots 128 px "
                                     "apart where a cubic does not follow it)")
    parser.add_argument("--saturation", type=saturation_option, default=None, metavar="ADU",
                        help=f"saturation level of the raw images, ADU: {saturation} "
                             f"({SATURATION_DEFAULT})")


def flat_edge_option(parser):
    """``--edge``: the border of each amplifier's flats left out of the statistics (None: the
    calibration's default, `bfpsf.calibration.flat_mask.DEFAULT_EDGE`)."""
    parser.add_argument("--edge", type=non_negative_int, default=None, metavar="PIXELS",
                        help="pixels masked along each side of each amplifier's flats, whose "
                             "edges collect less charge as the flux grows (default 10, as "
                             "cp_pipe's PTC; 0 keeps every pixel)")


def sky_degree_option(text):
    """``--sky-degree``: 'auto', 'spline' or 0, 1, 2, 3."""
    if text in ("auto", "spline"):
        return text
    if text not in ("0", "1", "2", "3"):
        raise argparse.ArgumentTypeError(f"must be auto, spline or 0, 1, 2, 3, got {text!r}")
    return int(text)


def maxlag_option(text):
    """``--maxlag``: 'auto' or a positive integer."""
    if text == "auto":
        return text
    try:
        return positive_int(text)
    except argparse.ArgumentTypeError:
        msg = f"expected 'auto' or a positive integer, got {text!r}"
        raise argparse.ArgumentTypeError(msg) from None


def _integer(text, minimum, expected):
    try:
        value = int(text)
    except ValueError:
        value = minimum - 1
    if value < minimum:
        msg = f"expected {expected}, got {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return value


def positive_int(text):
    """An integer option that must be at least 1 (counts, sizes, iterations)."""
    return _integer(text, 1, "a positive integer")


def stamp_size_option(text):
    """``--size`` / ``--stamp-size``: a stamp side of at least 8 pixels."""
    return _integer(text, 8, "an integer >= 8 pixels")


def non_negative_int(text):
    """An integer option that may be 0 (e.g. a number of samples)."""
    return _integer(text, 0, "an integer >= 0")


def _real(text, accept, expected):
    """A finite float option that ``accept(value)`` takes, else argparse's usage error."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and accept(value)):
        msg = f"expected {expected}, got {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return value


def background_option(text):
    """``--background``: a finite sky level (ADU per pixel)."""
    return _real(text, lambda value: True, "a finite sky level in ADU")


def finite_float(text):
    """A float option that may take any finite value (e.g. a non-linearity coefficient)."""
    return _real(text, lambda value: True, "a finite number")


def positive_float(text):
    """A float option that must be positive and finite (sizes, gains, times, peaks)."""
    return _real(text, lambda value: value > 0, "a positive finite number")


def non_negative_float(text):
    """A float option that may be 0 but must be finite (e.g. a read noise)."""
    return _real(text, lambda value: value >= 0, "a finite number >= 0")


def saturation_option(text):
    """``--saturation``: a positive finite level, ADU."""
    return _real(text, lambda value: value > 0, "a positive finite level in ADU")


def flat_level_option(text):
    """``--levels`` / ``--flat-levels``: a flat level, electrons per pixel, from 0 to
    `bfpsf.validation.simulate_flats.MAX_LEVEL_E`."""
    from ..validation.simulate_flats import MAX_LEVEL_E

    return _real(text, lambda value: 0 <= value <= MAX_LEVEL_E,
                 f"a flat level from 0 to {MAX_LEVEL_E:.0e} e- per pixel (10 times a CCD's "
                 "full well; GalSim's SiliconSensor pixel areas diverge beyond a few 1e6 e-)")


def add_common_options(parser):
    """Add the options every command shares (module docstring)."""
    common = parser.add_argument_group("common options")
    common.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bars on stderr (default: only when stderr is a terminal)")
    common.add_argument("-v", "--verbose", action="count", default=0,
                        help="more messages on stderr (-v: info, -vv: debug)")
    common.add_argument("-q", "--quiet", action="count", default=0,
                        help="fewer messages on stderr (errors only)")
    common.add_argument("--threads", type=positive_int, metavar="N",
                        help="threads for the FFTs and GalSim (default: OMP_NUM_THREADS if "
                             "set, else every CPU)")
    return parser


class _StderrHandler(logging.StreamHandler):
    """Log records to the current ``sys.stderr`` (which may be replaced after set-up), a
    warning after ``WARNING:`` as the commands' own (docs/hostile_input.md), the rest after
    ``bfpsf:``."""

    def emit(self, record):
        self.stream = sys.stderr
        super().emit(record)

    def format(self, record):
        prefix = record.levelname if record.levelno >= logging.WARNING else "bfpsf"
        return f"{prefix}: {record.getMessage()}"


def _apply_common_options(args):
    """Resolve the common options: logging, threads, and ``args.progress`` as a bool."""
    if not hasattr(args, "verbose"):  # e.g. ``bfpsf simulate`` without a target: only help
        return
    logger = logging.getLogger("bfpsf")
    level = logging.WARNING + 10 * (args.quiet - args.verbose)
    logger.setLevel(min(max(level, logging.DEBUG), logging.CRITICAL))
    if not any(isinstance(handler, _StderrHandler) for handler in logger.handlers):
        logger.addHandler(_StderrHandler())
    if args.progress is None:
        args.progress = sys.stderr.isatty()
    from ..resources import check_settings

    check_settings()
    threads = args.threads
    if threads is None and os.environ.get("OMP_NUM_THREADS", "").strip().isdigit():
        threads = int(os.environ["OMP_NUM_THREADS"])
    if threads is not None:
        if threads < 1:
            msg = f"--threads must be at least 1, got {threads}"
            raise BFPSFValueError(msg, threads)
        from ..model.tiles import set_default_workers

        os.environ["OMP_NUM_THREADS"] = str(threads)
        set_default_workers(threads)


def build_parser():
    parser = argparse.ArgumentParser(
        prog="bfpsf", description="Brighter-fatter aware PSF models (Guyonnet et al. 2015).")
    parser.add_argument("--version", action="version", version=f"bfpsf {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        module = importlib.import_module(f"{__name__}.{name}")
        sub = module.add_parser(subparsers)
        if getattr(module, "TARGETS", None) is None:  # simulate adds them to each target
            add_common_options(sub)
        sub.set_defaults(_run=module.run)
    return parser


#: Exit status after an interrupt (SIGINT, Ctrl-C), as shells report 128 + 2.
EXIT_INTERRUPTED = 130


def main(argv=None):
    """Run one command; every failure is one line on stderr and an exit status: 1 for an
    error, 2 for a usage error (argparse), 130 for an interrupt. Outputs are written
    atomically, so an interrupted or failed command leaves no partial file."""
    command = "bfpsf"
    args = None
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        command = " ".join(filter(None, ("bfpsf", args.command,
                                          getattr(args, "simulate_target", None))))
        if not hasattr(args, "_run"):
            parser.print_help()
            return 2
        _apply_common_options(args)
        with all_or_nothing():  # a command that stops leaves none of its new outputs
            return args._run(args) or 0
    except BFPSFError as error:
        print(f"{command}: error: {_one_line(error)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        # more Ctrl-C while the interrupt is being handled (the user presses it again) would
        # break the clean-up with a traceback: they are ignored until it is done (bounded by
        # the clusters' close timeout)
        with _interrupts_ignored():
            _close_dask_quietly()
            print(f"{command}: interrupted; no partial output was left", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as error:  # an operating-system error no library function turned into ours
        where = f"{error.filename}: " if error.filename else ""
        print(f"{command}: error: {where}{_one_line(error.strerror or error)}", file=sys.stderr)
        return 1
    except MemoryError:
        print(f"{command}: error: out of memory; give smaller sizes in the options or fewer "
              "inputs", file=sys.stderr)
        return 1
    except Exception as error:  # noqa: BLE001 -- a bug: one line, the traceback on request
        if args is not None and getattr(args, "verbose", 0) >= 2:
            import traceback

            traceback.print_exc()
        print(f"{command}: internal error: {type(error).__name__}: {_one_line(error)} (a "
              "bfpsf bug, please report it; -vv prints the traceback)", file=sys.stderr)
        return 1


@contextlib.contextmanager
def _interrupts_ignored():
    """SIGINT ignored inside the block (in the main thread; elsewhere nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _close_dask_quietly():
    """Close the local Dask clusters an interrupt left behind (one may be half-started),
    without the tracebacks Dask's own exit handler prints for a half-started one."""
    spec = sys.modules.get("distributed.deploy.spec")
    if spec is None:
        return
    import atexit
    import io

    logging.getLogger("distributed").setLevel(logging.CRITICAL)
    for cluster in list(spec.SpecCluster._instances):
        with contextlib.suppress(Exception), contextlib.redirect_stderr(io.StringIO()):
            cluster.close(timeout=10)
    atexit.unregister(spec.close_clusters)


def _one_line(error):
    """The first line of an error's message (astropy and numpy append tables and hints)."""
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


if __name__ == "__main__":
    sys.exit(main())
