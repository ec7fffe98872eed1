"""Write the figures of the README and docs/ from the runs that make them, each stamped with
the command that made it, the bfpsf version, the commit and the date.

    OMP_NUM_THREADS=1 python docs/make_figures.py                 # every figure, full runs
    OMP_NUM_THREADS=1 python docs/make_figures.py --only cp_pipe_amatrix shear_psf_size
    OMP_NUM_THREADS=1 python docs/make_figures.py --quick --output /tmp/figures  # a check

Each figure is drawn by its own command (an example script or a benchmark, `FIGURES`) in a
temporary directory, then copied into ``--output`` (default docs/examples) with a footer line
naming that command, so a figure cannot drift from the code without its stamp saying so. The
numbers the README and docs/ quote beside a figure are the full runs' (about 1 h in all, most
of it SiliconSensor); ``--quick`` runs every command's small variant (minutes) and stamps
"quick" on the figure, for checking the script, not for the docs.
"""

import argparse
import datetime
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.image  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402

import bfpsf  # noqa: E402
from bfpsf.outputs import save_figure  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

#: name: (the command's arguments after the interpreter, with {out} the run's directory; the
#: figure it writes, relative to {out}). The examples take --quick; so does the benchmark.
FIGURES = {
    "calibrate_from_flats": (["examples/calibrate_from_flats.py", "--output", "{out}"],
                             "calibrate_from_flats.png"),
    "crowded_field_photometry": (["examples/crowded_field_photometry.py", "--output", "{out}"],
                                 "crowded_field_photometry.png"),
    "shear_psf_size": (["examples/shear_psf_size.py", "--output", "{out}"],
                       "shear_psf_size.png"),
    "simulate_with_bf": (["examples/simulate_with_bf.py", "--output", "{out}"],
                         "simulate_with_bf.png"),
    "cp_pipe_amatrix": (["examples/cp_pipe_amatrix.py", "--output", "{out}"],
                        "cp_pipe_amatrix.png"),
    # the flats of docs/plugins.md's acceptance (seed 31), made by the benchmark itself
    "piff_residuals": (["benchmarks/bench_piff.py", "--workdir", "{out}/work", "--seed", "29",
                        "--flats-seed", "31", "--control", "--plot",
                        "{out}/piff_residuals.png", "--json", "{out}/result.json"],
                       "piff_residuals.png"),
}

#: Height of the footer added under a figure, pixels (its text is 8 points at the figure's dpi).
FOOTER_PIXELS = 18


def _commit():
    try:
        run = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=ROOT,
                             capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        return "no git commit"
    return run.stdout.strip()


def stamp(source, destination, line, *, overwrite=True, dpi=70):
    """Copy the PNG ``source`` to ``destination`` with ``line`` written in a footer below it."""
    pixels = matplotlib.image.imread(source)
    height, width = pixels.shape[:2]
    figure = plt.figure(figsize=(width / dpi, (height + FOOTER_PIXELS) / dpi), dpi=dpi)
    figure.figimage(pixels, xo=0, yo=FOOTER_PIXELS, origin="upper")
    figure.text(4 / width, 4 / (height + FOOTER_PIXELS), line, fontsize=8, color="0.3",
                ha="left", va="bottom")
    save_figure(figure, destination, overwrite=overwrite, dpi=dpi)


def make_figure(name, output, *, quick=False):
    """Run the command of figure ``name`` and write its stamped PNG into ``output``."""
    arguments, figure = FIGURES[name]
    with tempfile.TemporaryDirectory() as directory:
        argv = [part.format(out=directory) for part in arguments] + (["--quick"] if quick else [])
        subprocess.run([sys.executable, *argv], cwd=ROOT, check=True)
        shown = " ".join(part.format(out="OUT") for part in arguments)
        line = (f"python {shown}{' --quick (a check, not the docs figure)' if quick else ''}"
                f"  |  bfpsf {bfpsf.__version__} {_commit()}  |  "
                f"{datetime.date.today().isoformat()}")
        destination = Path(output) / figure
        stamp(Path(directory) / figure, destination, line)
    return destination


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="+", choices=sorted(FIGURES), metavar="NAME",
                        help=f"these figures only ({', '.join(FIGURES)})")
    parser.add_argument("--quick", action="store_true",
                        help="each command's small variant (minutes in all), stamped quick")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "examples",
                        help="directory of the figures (default docs/examples)")
    args = parser.parse_args(argv)
    args.output.mkdir(parents=True, exist_ok=True)
    for name in args.only or FIGURES:
        print(f"wrote {make_figure(name, args.output, quick=args.quick)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
