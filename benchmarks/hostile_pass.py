"""A fresh pass of hostile inputs against the ``bfpsf`` command line (issue 25), written after
the fixes and separate from the test bench (tests/test_hostile_input.py).

Each case runs ``python -m bfpsf ...`` in a fresh copy of the fixture directory, with the bfpsf
found on ``--pythonpath`` (so the same cases run against any commit), and is classified:

* ``clean``: the expected result: a one-line error (exit 1, or argparse's usage and error line
  with exit 2) where an error is due, or success with the checks passed;
* ``traceback``: a Python traceback, or bfpsf's one-line "internal error" (a bug caught);
* ``data loss``: an input file changed;
* ``killed / hang``: killed by a signal, over the memory cap, or over the time bound;
* ``accepted silently``: exit 0 where an error (or a flag) was due;
* ``other``: any other failure (several error lines, wrong exit status, a check failing).

Usage::

    python benchmarks/hostile_pass.py --pythonpath DIR --fixtures DIR [--cases NAME...]

The fixtures (simulated flats, a calibration, star images...) are made once by
``--make-fixtures`` with the bfpsf on ``--pythonpath``.
"""

import argparse
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CAP = 8 * 2**30       # the memory cap, bytes
BOUND = 60.0          # refusals within this, s
TIMEOUT = 240.0       # anything longer is a hang here


def make_fixtures(directory):
    """The input files of every case (GalSim flats and stars; seeds 31-36)."""
    from astropy.io import fits

    import galsim
    from bfpsf.model.galsim_profile import render_stars
    from bfpsf.validation.simulate_flats import write_flats

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    write_flats(directory / "flats", "lsst_e2v_50_8", [5e3, 2e4, 4e4, 6e4, 8e4, 1e5], pairs=2,
                size=96, nsteps=5, seed=31)
    rng = np.random.default_rng(32)

    def star_field(path, side, per_row, peak_flux, saturate=None, keyword="SATURATE"):
        grid = np.linspace(20, side - 20, per_row)
        xy = np.array([(x, y) for x in grid for y in grid])
        xy = xy + rng.uniform(-0.5, 0.5, xy.shape)
        flux = np.geomspace(2e4, peak_flux, len(xy))
        rng.shuffle(flux)
        image = render_stars(galsim.Moffat(beta=3.0, fwhm=3.0), xy, flux, (side, side)) + 300.0
        adu = (rng.poisson(image) + rng.normal(0.0, 5.0, image.shape)) / 1.5
        header = fits.Header({"EXPTIME": 10.0, "GAIN": 1.5})
        truth = 0
        if saturate is not None:
            rows, columns = np.rint(xy[:, 1]).astype(int), np.rint(xy[:, 0]).astype(int)
            truth = int(sum(adu[r - 4:r + 5, c - 4:c + 5].max() >= saturate
                            for r, c in zip(rows, columns)))
            adu = np.minimum(adu, saturate)
            header[keyword] = saturate
        fits.PrimaryHDU(adu.astype(np.float32), header=header).writeto(path, overwrite=True)
        return adu, truth

    truths = {}
    _, truths["sat.fits"] = star_field(directory / "sat.fits", 256, 8, 3e6, 35000.0)
    adu, truths["satlevel.fits"] = star_field(directory / "satlevel.fits", 256, 8, 3e6, 42000.0,
                                              keyword="SATLEVEL")
    star_field(directory / "big1.fits", 512, 12, 6e5)
    star_field(directory / "big2.fits", 512, 12, 6e5)
    # a two-amplifier file, SATURATE only in the primary header
    halves = [adu[:, :128], adu[:, 128:]]
    hdus = [fits.PrimaryHDU(header=fits.Header({"EXPTIME": 10.0, "SATURATE": 42000.0}))]
    for index, half in enumerate(halves):
        hdu = fits.ImageHDU(half.astype(np.float32), name=f"C0{index}")
        hdu.header["DETSEC"] = f"[{128 * index + 1}:{128 * index + 128},1:256]"
        hdus.append(hdu)
    fits.HDUList(hdus).writeto(directory / "mef_sat.fits", overwrite=True)
    truths["mef_sat.fits"] = truths["satlevel.fits"]
    sky = rng.normal(100.0, 5.0, (128, 128)).astype(np.float32)
    fits.PrimaryHDU(sky, header=fits.Header({"EXPTIME": 1.0, "GAIN": 1.5})).writeto(
        directory / "sky.fits", overwrite=True)
    for name, sections in (("overlap", ("[1:40,1:30]", "[31:50,1:30]", "[1:40,1:30]")),
                           ("outside", ("[1:40,1:30]", "[41:70,1:30]", "[1:40,1:30]")),
                           ("detsec", ("[1:40,1:30]", "[41:50,1:30]", "[1:40,1:30]"))):
        hdus = [fits.PrimaryHDU(header=fits.Header({"EXPTIME": 1.0}))]
        for index in range(2):
            hdu = fits.ImageHDU(rng.normal(1000.0, 30.0, (30, 50)).astype(np.float32),
                                name=f"A{index}")
            hdu.header["DATASEC"], hdu.header["BIASSEC"], detsec = sections
            if name != "detsec" or index == 0:
                detsec = f"[{40 * index + 1}:{40 * index + 40},1:30]"
            hdu.header["DETSEC"] = detsec
            hdus.append(hdu)
        fits.HDUList(hdus).writeto(directory / f"mef_{name}.fits", overwrite=True)
    (directory / "empty.fits").write_bytes(b"")
    (directory / "notes.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)
    (directory / "truths.json").write_text(json.dumps(truths))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    flats = sorted(str(path.relative_to(directory)) for path in (directory / "flats").glob("*"))
    for argv in (["calibrate", *flats, "-o", "cal.fits", "--workers", "1", "--n-monte-carlo",
                  "10", "-q"],
                 ["psf", "big1.fits", "big2.fits", "--calib", "cal.fits", "-o", "psf.fits"],
                 ["psf", "big1.fits", "big2.fits", "--calib", "cal.fits", "--grid", "2", "2",
                  "-o", "psfgrid.fits"],
                 ["measure", "big1.fits", "-o", "stars.ecsv"]):
        subprocess.run([sys.executable, "-m", "bfpsf", *argv], cwd=directory, check=True,
                       env=env, capture_output=True)
    (directory / "calibrations").mkdir(exist_ok=True)
    shutil.copy(directory / "cal.fits", directory / "calibrations" / "kalibrierung_ä.fits")


FLATS = "flats/*.fits"
# (class, name, argv, expected ('error' or 'ok'), options)
CASES = [
    # --- an output that is an input -------------------------------------------------------
    ("data loss", "measure -o its image", ["measure", "big1.fits", "-o", "big1.fits",
                                           "--overwrite"], "error", {}),
    ("data loss", "calibrate -o a flat via ../", ["calibrate", FLATS, "-o",
                                                  "flats/../flats/" + "FLAT0", "--overwrite",
                                                  "--workers", "1"], "error", {}),
    ("data loss", "psf -o its image", ["psf", "big1.fits", "--calib", "cal.fits", "-o",
                                       "big1.fits", "--overwrite"], "error", {}),
    ("data loss", "photometry -o its PSF", ["photometry", "big1.fits", "--psf", "psf.fits",
                                            "-o", "psf.fits", "--overwrite"], "error", {}),
    ("data loss", "slope --plot its table", ["slope", "stars.ecsv", "--plot", "stars.ecsv",
                                             "--overwrite"], "error", {}),
    ("data loss", "calibrate --export-ptc hard link", ["calibrate", FLATS, "-o", "c.fits",
                                                       "--export-ptc", "hard.fits",
                                                       "--overwrite", "--workers", "1"],
     "error", {"hardlink": ("FLAT0", "hard.fits")}),
    ("data loss", "diagnose --output-calib a flat", ["diagnose", "--flats", FLATS, "--images",
                                                     "big1.fits", "--output-calib", "FLAT0",
                                                     "--overwrite"], "error", {}),
    ("data loss", "measure --json its calibration", ["measure", "big1.fits", "--calib",
                                                     "cal.fits", "-o", "m.ecsv", "--json",
                                                     "cal.fits", "--overwrite"], "error", {}),
    ("data loss", "photometry -o absolute path", ["photometry", "big1.fits", "--psf",
                                                  "psf.fits", "-o", "ABS:big1.fits",
                                                  "--overwrite"], "error", {}),
    ("data loss", "psf -o symlink to calibration", ["psf", "big1.fits", "--calib", "cal.fits",
                                                    "-o", "link.fits", "--overwrite"], "error",
     {"symlink": ("cal.fits", "link.fits")}),
    # --- tracebacks: foreign files, names, empty images, file system, interrupts -----------
    ("traceback", "--from-ptc a PNG", ["calibrate", "--from-ptc", "notes.png", "-o",
                                       "c.fits"], "error", {}),
    ("traceback", "--from-ptc an empty file", ["calibrate", "--from-ptc", "empty.fits", "-o",
                                               "c.fits"], "error", {}),
    ("traceback", "--from-ptc a star table", ["calibrate", "--from-ptc", "stars.ecsv", "-o",
                                              "c.fits"], "error", {}),
    ("traceback", "psf with a non-ASCII calibration name",
     ["psf", "big1.fits", "--calib", "calibrations/kalibrierung_ä.fits", "-o", "p.fits"],
     "ok", {}),
    ("traceback", "calibrate to a non-ASCII name from non-ASCII flats",
     ["calibrate", "NONASCII_FLATS", "-o", "kalibrierung_€.fits", "--workers", "1",
      "--n-monte-carlo", "2"], "ok", {"nonascii_flats": True}),
    ("traceback", "diagnose on sky only", ["diagnose", "--flats", FLATS, "--images",
                                           "sky.fits"], "error", {}),
    ("traceback", "measure on sky only", ["measure", "sky.fits", "-o", "m.ecsv"], "ok", {}),
    ("traceback", "psf on sky only", ["psf", "sky.fits", "--calib", "cal.fits", "-o",
                                      "p.fits"], "error", {}),
    ("traceback", "photometry on sky only", ["photometry", "sky.fits", "--psf", "psf.fits",
                                             "-o", "p.ecsv"], "ok", {}),
    ("traceback", "psf product written past a 20 kB file limit",
     ["psf", "big1.fits", "--calib", "cal.fits", "-o", "p.fits"], "error", {"fsize": 20000}),
    ("traceback", "calibrate JSON past a 3 kB file limit",
     ["calibrate", FLATS, "-o", "c.fits", "--json", "c.json", "--workers", "1"], "error",
     {"fsize": 3000}),
    ("traceback", "SIGINT during psf", ["psf", "big1.fits", "big2.fits", "--calib", "cal.fits",
                                        "-o", "p.fits", "--json", "p.json"], "interrupt",
     {"sigint": 3.0}),
    ("traceback", "SIGINT during calibrate --workers 2", ["calibrate", FLATS, "-o", "c.fits",
                                                         "--workers", "2"], "interrupt",
     {"sigint": 9.0}),
    ("traceback", "photometry with the gridded product", ["photometry", "big1.fits", "--psf",
                                                          "psfgrid.fits", "-o", "p.ecsv"],
     "ok", {}),
    ("traceback", "slope --psf the gridded product", ["slope", "stars.ecsv", "--psf",
                                                      "psfgrid.fits"], "ok", {}),
    ("traceback", "measure a 3-D cube", ["measure", "CUBE", "--gain", "1", "-o", "m.ecsv"],
     "error", {"cube": True}),
    # --- accepted silently: counts and limits ---------------------------------------------
    ("accepted silently", "calibrate --n-monte-carlo -5", ["calibrate", FLATS, "-o", "c.fits",
                                                           "--n-monte-carlo", "-5",
                                                           "--workers", "1"], "error", {}),
    ("accepted silently", "calibrate --workers -2", ["calibrate", FLATS, "-o", "c.fits",
                                                     "--workers", "-2"], "error", {}),
    ("accepted silently", "diagnose --bins 0", ["diagnose", "--flats", FLATS, "--images",
                                                "big1.fits", "--bins", "0"], "error", {}),
    ("accepted silently", "measure --saturation -100", ["measure", "big1.fits", "-o", "m.ecsv",
                                                        "--saturation", "-100"], "error", {}),
    ("accepted silently", "psf --saturation nan", ["psf", "big1.fits", "--calib", "cal.fits",
                                                   "-o", "p.fits", "--saturation", "nan"],
     "error", {}),
    ("accepted silently", "simulate flats --pairs 0", ["simulate", "flats", "--pairs", "0",
                                                       "-o", "sim"], "error", {}),
    ("accepted silently", "validate --flat-pairs -1", ["validate", "--quick", "--flat-pairs",
                                                       "-1"], "error", {}),
    # --- saturation from the header alone -------------------------------------------------
    ("saturation", "measure flags every SATURATE star", ["measure", "sat.fits", "-o", "m.ecsv",
                                                         "--json", "m.json"], "ok",
     {"saturated": ("m.json", "n_saturated", "sat.fits")}),
    ("saturation", "photometry flags every SATURATE star",
     ["photometry", "sat.fits", "--psf", "psf.fits", "-o", "p.ecsv", "--json", "p.json"], "ok",
     {"saturated": ("p.json", "n_saturated", "sat.fits")}),
    ("saturation", "psf leaves out every SATLEVEL star",
     ["psf", "satlevel.fits", "--calib", "cal.fits", "-o", "p.fits", "--json", "p.json"], "ok",
     {"saturated": ("p.json", "n_saturated", "satlevel.fits")}),
    ("saturation", "measure a MEF with SATURATE in the primary",
     ["measure", "mef_sat.fits", "-o", "m.ecsv", "--gain", "1.5", "--json", "m.json"], "ok",
     {"saturated": ("m.json", "n_saturated", "mef_sat.fits")}),
    # --- amplifier sections -----------------------------------------------------------------
    ("sections", "BIASSEC overlapping DATASEC", ["measure", "mef_overlap.fits", "--gain", "1",
                                                 "-o", "m.ecsv"], "error", {}),
    ("sections", "BIASSEC outside the HDU", ["measure", "mef_outside.fits", "--gain", "1",
                                             "-o", "m.ecsv"], "error", {}),
    ("sections", "overlapping DETSECs", ["measure", "mef_detsec.fits", "--gain", "1", "-o",
                                         "m.ecsv"], "error", {}),
    # --- memory and time under an 8 GiB cap -----------------------------------------------
    ("memory / time", "psf --grid 200 200", ["psf", "big1.fits", "--calib", "cal.fits", "-o",
                                             "p.fits", "--grid", "200", "200"], "error",
     {"cap": CAP}),
    ("memory / time", "psf --grid 30 30", ["psf", "big1.fits", "--calib", "cal.fits", "-o",
                                           "p.fits", "--grid", "30", "30"], "error",
     {"cap": CAP}),
    ("memory / time", "psf --oversampling 64 --size 99",
     ["psf", "big1.fits", "--calib", "cal.fits", "-o", "p.fits", "--oversampling", "64",
      "--size", "99"], "error", {"cap": CAP}),
    ("memory / time", "measure --stamp-size 4001", ["measure", "big1.fits", "-o", "m.ecsv",
                                                    "--stamp-size", "4001"], "error",
     {"cap": CAP}),
    ("memory / time", "simulate flats --size 60000", ["simulate", "flats", "--size", "60000",
                                                      "-o", "sim"], "error", {"cap": CAP}),
    ("memory / time", "calibrate --n-monte-carlo 10^9", ["calibrate", FLATS, "-o", "c.fits",
                                                         "--n-monte-carlo", "1000000000",
                                                         "--workers", "1"], "error",
     {"cap": CAP}),
    ("memory / time", "calibrate --maxlag 200 --model exponential",
     ["calibrate", FLATS, "-o", "c.fits", "--maxlag", "200", "--model", "exponential",
      "--workers", "1"], "error", {"cap": CAP}),
]


def _prepare(case_dir, argv, options, fixtures):
    flats = sorted(str(path.relative_to(fixtures)) for path in (fixtures / "flats").glob("*"))
    out = []
    for arg in argv:
        if arg == FLATS:
            out.extend(flats)
        elif arg == "FLAT0":
            out.append(flats[0])
        elif arg.startswith("flats/../flats/FLAT0"):
            out.append("flats/../" + flats[0])
        elif arg.startswith("ABS:"):
            out.append(str(case_dir / arg[4:]))
        elif arg == "NONASCII_FLATS":
            for flat in flats:
                target = case_dir / ("ü_" + Path(flat).name)
                shutil.copy(case_dir / flat, target)
                out.append(target.name)
        elif arg == "CUBE":
            from astropy.io import fits

            fits.PrimaryHDU(np.ones((3, 20, 20), dtype=np.float32)).writeto(case_dir / "cube.fits")
            out.append("cube.fits")
        else:
            out.append(arg)
    if "hardlink" in options:
        source, link = options["hardlink"]
        os.link(case_dir / (flats[0] if source == "FLAT0" else source), case_dir / link)
    if "symlink" in options:
        source, link = options["symlink"]
        os.symlink(source, case_dir / link)
    return out


def _snapshot(directory):
    return {str(path.relative_to(directory)): path.read_bytes()
            for path in sorted(directory.rglob("*")) if path.is_file()}


def run_case(case, fixtures, pythonpath):
    kind, name, argv, expected, options = case
    with tempfile.TemporaryDirectory(prefix="hostile_") as temporary:
        case_dir = Path(temporary) / "work"
        shutil.copytree(fixtures, case_dir, symlinks=True)
        argv = _prepare(case_dir, argv, options, fixtures)
        before = _snapshot(case_dir)

        def limits():
            if "cap" in options:
                resource.setrlimit(resource.RLIMIT_AS, (options["cap"], options["cap"]))
            if "fsize" in options:
                resource.setrlimit(resource.RLIMIT_FSIZE, (options["fsize"],) * 2)
            signal.signal(signal.SIGINT, signal.SIG_DFL)

        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(pythonpath),
               "MPLBACKEND": "Agg"}
        start = time.monotonic()
        process = subprocess.Popen([sys.executable, "-m", "bfpsf", *argv], cwd=case_dir,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                   env=env, preexec_fn=limits)
        if "sigint" in options:
            time.sleep(options["sigint"])
            process.send_signal(signal.SIGINT)
        try:
            out, err = process.communicate(timeout=TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            out, err = process.communicate()
            return kind, name, "killed / hang", f"over {TIMEOUT:.0f} s"
        seconds = time.monotonic() - start
        after = _snapshot(case_dir)
        code = process.returncode
        changed = [path for path in before if after.get(path) != before[path]]
        new = sorted(set(after) - set(before))
        lines = [line for line in err.splitlines() if line.strip()
                 and not line.startswith(("WARNING", "bfpsf: "))]
        detail = (lines[-1] if lines else "")[:160]
        if changed:
            return kind, name, "data loss", f"changed {changed[:3]}"
        if code < 0 or "MemoryError" in err or "out of memory" in err:
            return kind, name, "killed / hang", f"exit {code}: {detail}"
        if "Traceback" in err or "internal error" in err:
            return kind, name, "traceback", detail
        if "cap" in options and seconds > BOUND:
            return kind, name, "killed / hang", f"{seconds:.0f} s > {BOUND:.0f} s: {detail}"
        if expected == "interrupt":
            ok = code == 130 and len(err.strip().splitlines()) == 1 and not new
            return kind, name, "clean" if ok else "other", f"exit {code}, {len(new)} new " \
                                                           f"files: {err.strip()[-160:]}"
        if expected == "error":
            if code == 0:
                return kind, name, "accepted silently", f"exit 0: {out.strip()[-120:]}"
            one_line = (code == 1 and len(lines) == 1) or (code == 2 and lines
                                                            and "error:" in lines[-1])
            return kind, name, "clean" if one_line else "other", f"exit {code}: {detail}"
        if code != 0:
            return kind, name, "other", f"exit {code}: {detail}"
        if "saturated" in options:
            summary, key, image = options["saturated"]
            truth = json.loads((fixtures / "truths.json").read_text())[image]
            try:
                found = json.loads((case_dir / summary).read_text()).get(key)
            except (OSError, ValueError):
                found = None
            if found != truth:
                return kind, name, "accepted silently", f"{found} saturated reported, truth {truth}"
        return kind, name, "clean", f"exit 0 ({seconds:.0f} s)"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pythonpath", required=True, help="where the bfpsf to test is")
    parser.add_argument("--fixtures", required=True, help="fixture directory")
    parser.add_argument("--make-fixtures", action="store_true")
    parser.add_argument("--cases", nargs="*", help="run only these case names")
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args(argv)
    fixtures = Path(args.fixtures).resolve()
    if args.make_fixtures:
        make_fixtures(fixtures)
        return 0
    results = []
    for case in CASES:
        if args.cases and case[1] not in args.cases:
            continue
        result = run_case(case, fixtures, Path(args.pythonpath).resolve())
        results.append(result)
        print(f"{result[2]:18s} | {result[0]:18s} | {result[1]:45s} | {result[3]}", flush=True)
    counts = {}
    for kind, _, outcome, _ in results:
        counts.setdefault(kind, {}).setdefault(outcome, 0)
        counts[kind][outcome] += 1
    print(json.dumps(counts, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps({"results": results, "counts": counts}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
